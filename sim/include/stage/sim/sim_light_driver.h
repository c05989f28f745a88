// A simulated LED controller behind the LightDriver interface: holds the pattern table, steps on slot edges given
// by the simulator (Step()), and reports its channel outputs. Safety behaviour (blackout latch) as on hardware.
//
// Attached to the simulated world (AttachWorld) it steps on the world's slot clock by itself, as a board steps on
// its slot-clock input, and tells the world what its channels emit and when: at each edge plus the node's switch
// delay (plus any extra delay, a fault knob). Detached or destroyed, it leaves the world, which then sees it dark.
#pragma once

#include <atomic>
#include <climits>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/status.h"
#include "stage/light/light_driver.h"

namespace stage::sim {

class WorldClient;

struct SimLightWorld {
  // Not owned; must outlive the attachment.
  WorldClient* world = nullptr;
  // This node's index in the rig (its emission in the world).
  int node_index = 0;
  // Edge to switch, ns: the node's switch delay, the rig's extra delay for it (light_nodes[].sim.extra_delay_us) and
  // a fault's delay (sim.faults, or injected at run time, which replaces it).
  int64_t switch_delay_ns = 0;
  int64_t extra_delay_ns = 0;
  int64_t fault_delay_ns = 0;
  // A crash (fault) once the world passes this time (world clock; < 0: never): `on_crash` runs (a node process kills
  // itself), or without one the node leaves the world and goes dark.
  int64_t crash_at_ns = -1;
  std::function<void()> on_crash;
  // Called at every edge with its time since slot 0, ns (a fake board's timed faults).
  std::function<void(int64_t since_slot0_ns)> on_edge;
};

class SimLightDriver final : public light::LightDriver {
 public:
  SimLightDriver(std::string node_id, uint32_t channel_count);
  ~SimLightDriver() override;

  light::DriverDescription Describe() const override;
  absl::Status LoadPatternTable(const light::PatternTable& table) override;
  absl::Status Arm() override;
  absl::Status Disarm() override;
  absl::Status Blackout() override;
  absl::Status ResetBlackout() override;
  light::DriverState State() const override;
  // The table's first row at a planned edge of a free-running clock (an external generator). In a lockstep world an
  // armed node that waits for its StartAt holds the world at the edge it stands at (time stands still while the
  // controller plans, as it does for every device).
  absl::Status StartAt(int64_t first_edge_ns) override;
  // The world's edges as this node saw them (slots are the bus's).
  absl::StatusOr<light::ClockInput> SlotClockInput() const override;

  // A slot-clock edge: when armed, applies the next row of the table.
  void Step();
  // The levels on the channels now (all zero when dark).
  light::ChannelLevels Outputs() const;

  // Joins the world and steps on its edges from slot 0 on (see above). Once only.
  absl::Status AttachWorld(const SimLightWorld& world);
  // Leaves the world (the node goes dark there) and stops stepping. Idempotent.
  void DetachWorld();
  // Slot edges the node stepped on late (real-time world: the process fell behind; it catches up).
  uint64_t late_edges() const { return late_edges_.load(); }

 private:
  void WorldLoop(int device);
  // An edge of the world: steps the table (catching up `missed` edges), or keeps it dark until its planned first edge.
  void StepOnEdge(int64_t slot, int64_t time_ns, int64_t missed, int64_t run_end, int64_t half_period_ns);
  // Lockstep: waits while the armed table waits for a StartAt that has not come (or the node leaves the world).
  void HoldForStart();

  std::string node_id_;
  uint32_t channel_count_;
  mutable std::mutex mutex_;
  light::PatternTable table_;  // guarded by mutex_
  bool table_loaded_ = false;  // guarded by mutex_
  light::DriverState state_;   // guarded by mutex_
  // The armed table's planned first edge (StartAt), kStartNotYet while it waits for one, -1 once it started (or it
  // steps from the next edge); guarded by mutex_, changes signalled on start_changed_.
  int64_t start_at_ns_ = -1;
  int64_t start_requested_ns_ = -1;  // the StartAt asked last since the arm, -1 none
  bool attached_ = false, lockstep_ = false;  // in a world (AttachWorld), and whether it steps in lockstep
  std::condition_variable start_changed_;
  // The clock as seen: the last edge, the end of its run, the table's first edge; guarded by mutex_.
  light::ClockInput input_;
  int64_t input_run_end_ = -1;
  int64_t half_period_ns_ = 0;
  SimLightWorld world_;
  int world_device_ = -1;
  std::atomic<bool> detaching_{false};
  std::atomic<uint64_t> late_edges_{0};
  // What the world has been told, guarded by report_mutex_: the last switch reported and the watermark promised (no
  // change may come before it, except a blackout, which is a fault of the stage).
  std::mutex report_mutex_;
  int64_t last_switch_ns_ = INT64_MIN;
  int64_t promised_ns_ = INT64_MIN;
  std::thread world_thread_;
};

}  // namespace stage::sim
