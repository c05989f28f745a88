// A camera as the camera node sees it. Implementations: SimCameraDevice (sim/), AravisCameraDevice (camera-node/src/aravis/).
// No backend library appears in this header.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace stage::camera {

enum class TriggerMode {
  // Exposes on each edge of its hardware trigger line (or, for the sim, each Trigger() call from the bus).
  kHardware,
  // Exposes on each Trigger() call; the node calls it at scheduled times.
  kSoftware,
  // Exposes continuously at frame_rate_hz once started.
  kFreeRun,
};

// What the node asks of the camera. Values are as in the rig file; the device checks them against what it can do.
struct CameraSettings {
  uint32_t width = 0;
  uint32_t height = 0;
  // GenICam PFNC name: "Mono8", "BayerRG8", ...
  std::string pixel_format = "BayerRG8";
  double frame_rate_hz = 24;
  double exposure_us = 1000;
  double gain_db = 0;
  TriggerMode trigger = TriggerMode::kHardware;
};

// One delivered image. Frames are shared read-only between recorder and preview (no copies). The pixels are either
// the frame's own (`data`: the simulator) or lent from the device's buffer pool (`lent`, kept out of the pool by
// `lent_owner` until the last reference to the frame goes: zero copy from the network stack's buffer to the file).
struct Frame {
  // The camera's frame counter, from 0 at Start().
  uint64_t frame_id = 0;
  // Start of exposure on the camera's clock, ns.
  int64_t device_timestamp_ns = 0;
  uint32_t width = 0;
  uint32_t height = 0;
  std::string pixel_format;
  double exposure_us = 0;
  // Some of the frame's data never arrived (packets lost on the link): what arrived is kept, the rest is zero, and
  // `incomplete` says why ("missing packets: 3 of 1402"). Empty for a whole frame.
  std::string incomplete;
  // Row-major pixels, bytes_per_pixel * width * height bytes: the frame's own.
  std::vector<uint8_t> data;
  // Or the device's buffer, lent (see above).
  std::span<const uint8_t> lent;
  std::shared_ptr<const void> lent_owner;

  std::span<const uint8_t> pixels() const { return lent.data() != nullptr ? lent : std::span<const uint8_t>(data); }
};

// Receives frames. Called on the device's acquisition thread; must return quickly (hand off, never block on I/O).
class FrameSink {
 public:
  virtual ~FrameSink() = default;
  virtual void OnFrame(std::shared_ptr<const Frame> frame) = 0;
};

struct CameraDescription {
  std::string backend;  // "sim", "aravis"
  std::string vendor;
  std::string model;
  std::string serial;
};

class CameraDevice {
 public:
  virtual ~CameraDevice() = default;

  virtual CameraDescription Describe() const = 0;

  // Applies `settings` and reads them back. Only while stopped. InvalidArgument names the setting and what the camera
  // allows; FailedPrecondition if acquiring.
  virtual absl::Status Configure(const CameraSettings& settings) = 0;

  // Starts acquisition; frames go to `sink` on the device's thread until Stop() returns. `sink` must outlive Stop().
  virtual absl::Status Start(FrameSink* sink) = 0;

  // Stops acquisition; after it returns no more calls reach the sink. Idempotent.
  virtual absl::Status Stop() = 0;

  // One software trigger (TriggerMode::kSoftware). FailedPrecondition when not started or in another mode.
  virtual absl::Status Trigger() = 0;
};

}  // namespace stage::camera
