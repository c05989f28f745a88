// The GPIO lines a GpiodLightDriver drives and reads, behind an interface: the real ones are libgpiod's (gpiod_lines.cc,
// the only file that includes gpiod.hpp); tests give the driver fake lines, so the stepping logic is tested without
// hardware.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace stage::light {

class GpioLines {
 public:
  virtual ~GpioLines() = default;

  // In words, for messages: "gpiochip0 [gpio-sim.0-node0], 40 outputs, slot clock in on line 40".
  virtual std::string Describe() const = 0;

  // Sets every output line at once, in the order they were opened (0 or 1 each).
  virtual absl::Status SetOutputs(const std::vector<uint8_t>& values) = 0;

  // Slot clock as an input: waits up to `timeout` for rising edges and returns each one's kernel timestamp
  // (CLOCK_MONOTONIC, ns), oldest first; empty on timeout. All edges that queued up since the last call come back, so
  // a reader that fell behind still sees every edge.
  virtual absl::StatusOr<std::vector<int64_t>> WaitEdges(std::chrono::nanoseconds timeout) = 0;

  // Slot clock as an output (this node is the sync generator): drives the line.
  virtual absl::Status SetClock(bool high) = 0;
};

struct GpiodLinesOptions {
  // Chip by name ("gpiochip0"), path ("/dev/gpiochip0"), label or number.
  std::string chip;
  // Output lines, in the order SetOutputs takes their values.
  std::vector<uint32_t> outputs;
  // The slot clock line, if any: an input with rising-edge events, or an output when `drives_slot_clock`.
  std::optional<uint32_t> slot_clock_line;
  bool drives_slot_clock = false;
  // Consumer name the kernel shows for the requested lines (gpioinfo).
  std::string consumer = "fastage-light";
};

// Opens the chip and requests the lines (outputs low). NotFound / Unavailable name the chip, the line and the cause
// ("gpiochip0 line 40: Device or resource busy"); Unimplemented where this build has no libgpiod.
absl::StatusOr<std::unique_ptr<GpioLines>> OpenGpiodLines(const GpiodLinesOptions& options);

}  // namespace stage::light
