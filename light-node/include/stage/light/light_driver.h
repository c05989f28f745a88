// An LED controller as the light node sees it. Implementations: SimLightDriver (sim/), ModbusLightDriver and
// GpiodLightDriver (light-node/src/). No backend library appears in this header.
#pragma once

#include <climits>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace stage::light {

// Intensity per channel, 0..65535 (16-bit, as LED boards hold it). Index = channel.
using ChannelLevels = std::vector<uint16_t>;

// The rows a driver steps through, one per pattern; row r applies in slots k with k mod rows == r.
struct PatternTable {
  std::string pattern_set;
  std::vector<std::string> row_names;
  std::vector<ChannelLevels> rows;
};

enum class DriverMode {
  kIdle,      // dark, accepting a table
  kArmed,     // table verified, stepping on the slot clock
  kBlackout,  // dark and latched until ResetBlackout()
};

// The slot clock as a driver that sees its edges measures it (gpiod: kernel timestamps of the input line, or the
// times it drove its own clock line), since Arm().
struct EdgeTiming {
  uint64_t count = 0;
  // Edges that never reached the driver (a gap of more than 1.5 periods); the table stepped over their slots.
  uint64_t lost_edges = 0;
  // Mean period since Arm() and the largest deviation of one period from the nominal slot period (jitter), ns.
  double period_mean_ns = 0;
  double period_max_deviation_ns = 0;
  // Longest time from an edge to the outputs being set for it, ns.
  int64_t max_step_latency_ns = 0;
};

struct DriverState {
  DriverMode mode = DriverMode::kIdle;
  uint32_t channel_count = 0;
  // Row applied now, or -1 when dark.
  int current_row = -1;
  uint64_t steps = 0;
  // Faults in words ("over-temperature on channel 7"); empty when healthy.
  std::vector<std::string> faults;
  // Faults seen since the last Arm(), with when they started, kept after they clear (a take's record); empty when the
  // take ran clean.
  std::vector<std::string> take_faults;
  // Board temperature, degC, where the hardware reports one.
  std::optional<double> temperature_c;
  // Where the driver sees the slot-clock edges itself; unset where a board steps on them out of its sight.
  std::optional<EdgeTiming> edges;
};

// The slot-clock input as a driver that sees its edges reports it (the witness of an external generator). Edges are
// numbered on the line: the first after a silence by its time since the driver's epoch, then one per edge (lost ones
// counted). Times on the stage's clock (CLOCK_REALTIME; the world's clock in simulation).
struct ClockInput {
  bool running = false;  // the last edge is less than 1.5 periods old (simulation: the bus's run has not ended)
  int64_t last_slot = -1;
  int64_t last_edge_ns = 0;
  // The edge that applied the armed table's first row after StartAt(), and its number; -1 until it came.
  int64_t table_first_slot = -1;
  int64_t table_first_edge_ns = -1;
};

// StartAt(kStartNotYet): the armed table waits, dark, until a StartAt() names its edge.
inline constexpr int64_t kStartNotYet = INT64_MAX;

// A clock line is running while its last edge is younger than this many periods, and at least kQuietLineMinNs: one
// late edge (a busy host) is not a stopped generator.
inline constexpr int64_t kQuietLinePeriods = 4;
inline constexpr int64_t kQuietLineMinNs = 100'000'000;

struct DriverDescription {
  std::string backend;  // "sim", "modbus", "gpiod"
  std::string device;   // board address, chip name
  uint32_t channel_count = 0;
};

class SlotClockGenerator;

class LightDriver {
 public:
  virtual ~LightDriver() = default;

  virtual DriverDescription Describe() const = 0;

  // Loads `table` into the controller and reads it back. Only in kIdle. InvalidArgument names the row and channel
  // of a bad entry (wrong row width); FailedPrecondition in another mode.
  virtual absl::Status LoadPatternTable(const PatternTable& table) = 0;

  // kIdle -> kArmed: from now on each slot-clock edge steps to the next row. Needs a loaded table.
  virtual absl::Status Arm() = 0;

  // kArmed -> kIdle, outputs dark.
  virtual absl::Status Disarm() = 0;

  // All channels off now, from any mode, latched until ResetBlackout(). Must succeed even when the controller is
  // lost; an error means the hardware could not be reached and the lights may still be on.
  virtual absl::Status Blackout() = 0;
  virtual absl::Status ResetBlackout() = 0;

  virtual DriverState State() const = 0;
  // The slot clock this driver generates (a gpiod node with drives_slot_clock), owned by the driver; null for one
  // that steps on a clock it does not drive.
  virtual SlotClockGenerator* slot_clock() { return nullptr; }

  // A slot clock that runs free (an external generator): the armed table's first row applies at the first edge at or
  // after `first_edge_ns` - half a slot (kStartNotYet: not until a later StartAt names it); dark until then, and the
  // stepping starts over. Asked again for the same edge (a retried request), it changes nothing. Only armed;
  // FailedPrecondition where the driver does not see the edges itself (a board that steps on every edge from arming),
  // or an edge at or after that time has already passed (the table would start late).
  virtual absl::Status StartAt(int64_t first_edge_ns) {
    (void)first_edge_ns;
    return absl::FailedPreconditionError(absl::StrCat(
        Describe().backend, " light driver: its board steps on every slot-clock edge from arming, out of the node's "
        "sight, so its first row cannot be placed at a planned edge of a free-running clock"));
  }
  // The slot-clock input as this driver sees it; FailedPrecondition where it does not see the edges.
  virtual absl::StatusOr<ClockInput> SlotClockInput() const {
    return absl::FailedPreconditionError(
        absl::StrCat(Describe().backend, " light driver: it does not see the slot clock's edges"));
  }
};

}  // namespace stage::light
