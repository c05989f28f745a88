// LED channels on GPIO lines (libgpiod, through the GpioLines interface): the table lives in the node's memory, and
// each rising edge of the slot clock sets every channel's lines to the next row at once.
//
// A channel has `lines_per_channel` output lines, binary weighted, most significant first (one line: on/off; four:
// 16 levels through a resistor ladder or current-sink bank). A 16-bit table level is rounded to the nearest code;
// the worst rounding error of a table is logged when it is loaded and reported in Describe().
//
// The slot clock is either an input line, whose edges come with the kernel's timestamps (CLOCK_MONOTONIC), or,
// on the node that is the sync generator, an output line this driver drives itself at the rig's slot rate while
// armed (a run of the bus, as the simulated world runs one per take): rising edge at each slot start, high for
// `clock_duty` of the slot, timed by timing::SlotClock (absolute sleeps on CLOCK_MONOTONIC, 1 ns timer slack; a slot
// reached late is missed, not late). Either way every edge of the take is recorded (MeasuredEdges): the take's
// measured edges, for the timing comparison. On an input, a gap of more than 1.5 periods between two edges is edges
// lost (the kernel's v1 event queue holds 16); on the generator, the slots it skipped are: they are counted,
// reported, and the table steps over their slots.
//
// libgpiod v1 sets at most 64 lines per request: a node with more outputs sets a row in several writes, 64 lines
// each, microseconds apart.
#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "gpio_lines.h"
#include "stage/light/light_driver.h"
#include "stage/light/slot_clock.h"
#include "stage/timing/slot_clock.h"
#include "stage/v1/rig.pb.h"

namespace stage::light {

struct GpiodDriverOptions {
  std::string node_id;
  uint32_t channel_count = 0;
  // Output lines per channel, binary weighted (MSB first). 1..16. Default 1 (on/off).
  uint32_t lines_per_channel = 1;
  // The chip and lines: outputs are channel_count * lines_per_channel lines, channel c's at [c*k, c*k+k).
  GpiodLinesOptions lines;
  // The rig's slot rate, Hz (the nominal period edges are measured against; the generator's rate, a whole number).
  // Default 912.
  double slot_rate_hz = 912;
  // Generator: the clock's high time as a fraction of the slot, (0, 0.5]. Default 0.5.
  double clock_duty = 0.5;
  // Edges kept per take for MeasuredEdges() (the oldest are dropped beyond it). Default 65536 (72 s at 912 Hz).
  size_t edge_log_capacity = 65536;
  // Run the thread that waits for (or generates) slot-clock edges. Tests of the stepping logic turn it off and
  // call OnEdge() themselves. Default true.
  bool run_edge_thread = true;

  absl::Status Validate() const;
};

// Options for a gpiod light node of the rig (chip, lines, clock role), at the rig's slot rate.
absl::StatusOr<GpiodDriverOptions> GpiodDriverOptionsFromRig(const v1::LightNodeConfig& config, double slot_rate_hz);

// The slot-clock edges of a take (since Arm()), as measured: kernel timestamps of the input line's rising edges, or
// the times this node drove its own clock line high. CLOCK_MONOTONIC ns.
struct MeasuredEdges {
  std::vector<int64_t> times_ns;  // the last edge_log_capacity edges, oldest first
  EdgeTiming timing;              // over every edge since Arm(), including any dropped from times_ns
};

// Worst rounding of a table, as a fraction of full scale, above which loading it logs a warning (half an 8-bit step).
inline constexpr double kQuantizationWarning = 0.5 / 255;

// The line values of one row: per channel its code's bits, MSB first. Codes round `levels` to 2^k - 1 steps.
std::vector<uint8_t> RowLineValues(const ChannelLevels& levels, uint32_t lines_per_channel);

class GpiodLightDriver final : public LightDriver {
 public:
  // Opens the chip and requests the lines (libgpiod). Errors name the node, the chip and the line.
  static absl::StatusOr<std::unique_ptr<GpiodLightDriver>> Open(GpiodDriverOptions options);
  // With given lines (fakes in tests). The options' lines are only described, not opened.
  static absl::StatusOr<std::unique_ptr<GpiodLightDriver>> Create(GpiodDriverOptions options,
                                                                  std::unique_ptr<GpioLines> lines);
  // Stops the edge thread and sets every output low.
  ~GpiodLightDriver() override;

  DriverDescription Describe() const override;
  absl::Status LoadPatternTable(const PatternTable& table) override;
  absl::Status Arm() override;
  absl::Status Disarm() override;
  absl::Status Blackout() override;
  absl::Status ResetBlackout() override;
  DriverState State() const override;
  // The clock output as runs the controller plans (drives_slot_clock; null otherwise): see SlotClockGenerator. Slots
  // count from the driver's epoch (its creation, to the second, on CLOCK_REALTIME: the PTP-disciplined clock T0 is
  // in); edges come only in runs, at epoch + slot / rate, never between them.
  SlotClockGenerator* slot_clock() override { return slot_clock_.get(); }
  absl::StatusOr<v1::SlotClockRun> RunClock(const v1::SlotClockRunRequest& request);
  absl::StatusOr<v1::SlotClockRun> EndClock(int64_t align_slots);
  absl::StatusOr<v1::SlotClockRun> ClockRun() const;
  // A free-running clock on the input (an external generator): see LightDriver. Edge times are the kernel's
  // CLOCK_MONOTONIC stamps moved onto CLOCK_REALTIME (the clock T0 is in) by the offset between the two now.
  absl::Status StartAt(int64_t first_edge_ns) override;
  absl::StatusOr<ClockInput> SlotClockInput() const override;

  // One slot-clock edge at `time_ns` (CLOCK_MONOTONIC): armed, the next row goes out on the lines. `lost_before`:
  // edges lost just before this one where the caller knows (the generator's skipped slots); unset, a gap of more
  // than 1.5 periods since the last edge says so.
  void OnEdge(int64_t time_ns, std::optional<uint64_t> lost_before = std::nullopt);
  MeasuredEdges Edges() const;
  // The worst rounding error of the loaded table, as a fraction of full scale (0 when none is loaded).
  double quantization_error() const;

 private:
  GpiodLightDriver(GpiodDriverOptions options, std::unique_ptr<GpioLines> lines);
  // A run [first, first + count) on the generator (mutex_ held).
  absl::Status StartGenerator(int64_t first, int64_t count);
  // The slot passing now on the clock's epoch, and the run as the contract says it (mutex_ held).
  int64_t SlotNow() const;
  // The time of `slot`'s edge on CLOCK_REALTIME: epoch + slot / rate.
  int64_t EdgeNs(int64_t slot) const;
  v1::SlotClockRun RunNow() const;
  // CLOCK_REALTIME - CLOCK_MONOTONIC now; the number of the last input edge since the arm (-1 none; mutex_ held).
  static int64_t RealtimeOffsetNs();
  int64_t LastSlot() const;
  void StopGenerator();
  void InputLoop();
  void OnGeneratedEdge(const timing::SlotEdge& edge);
  // The generator's run of slots up to generator_end is over, its last missed_at_end skipped.
  void OnGeneratedRunEnd(int64_t generator_end, int64_t missed_at_end);
  // The generator reached `slot`, at or past the run's end, skipping the missed_before slots before it. mutex_ held.
  void PassedRunEndLocked(int64_t slot, int64_t missed_before);
  // Slots of a run that never went out (the generator passed them): counted as lost, and the table steps over them.
  // mutex_ held.
  void CountLostLocked(uint64_t lost);
  // With mutex_ held: a fault now and in the take's record, once per kind (`detail` is what varies: an error text).
  void NoteFault(const std::string& kind, const std::string& detail = "");
  absl::Status AllLow();
  std::string Who() const;

  GpiodDriverOptions options_;
  std::unique_ptr<GpioLines> lines_;
  mutable std::mutex mutex_;
  std::vector<std::vector<uint8_t>> row_lines_;   // guarded by mutex_: the table as line values
  double quantization_error_ = 0;                 // guarded by mutex_
  bool table_loaded_ = false;                     // guarded by mutex_
  DriverState state_;                             // guarded by mutex_
  std::deque<int64_t> edges_;                     // guarded by mutex_: the last edge_log_capacity edges
  EdgeTiming timing_;                             // guarded by mutex_: since Arm()
  int64_t first_edge_ns_ = 0, last_edge_ns_ = 0;  // guarded by mutex_
  int64_t armed_at_ns_ = 0;                       // guarded by mutex_
  // The armed table's planned first edge on CLOCK_MONOTONIC (StartAt), kStartNotYet while it waits for one, -1 once
  // it started or when it steps from the next edge; the number of the first edge since the arm (its time since the
  // epoch; a silence later counts as edges lost, it does not renumber), and the table's first edge (-1 none). Guarded
  // by mutex_.
  int64_t start_at_mono_ns_ = -1;
  int64_t start_requested_ns_ = -1;  // the StartAt asked last since the arm (CLOCK_REALTIME), -1 none
  int64_t line_first_slot_ = 0;
  int64_t table_first_slot_ = -1, table_first_edge_ns_ = -1;
  std::atomic<bool> stopping_{false};
  std::thread edge_thread_;                       // input: waits for edges
  std::unique_ptr<timing::SlotClock> generator_;  // guarded by mutex_: the current run's clock
  // The clock's runs: its epoch (CLOCK_REALTIME ns), the last run [run_first_, run_end_) (an EndClock shortens it), and
  // the last slot whose edge went out (-1 none); run_first_ < 0 before the first run.
  int64_t epoch_ns_ = 0;
  int64_t run_first_ = -1, run_end_ = -1, run_current_ = -1;  // guarded by mutex_
  std::unique_ptr<SlotClockGenerator> slot_clock_;
};

}  // namespace stage::light
