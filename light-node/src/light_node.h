// The light node's logic: owns the driver, answers for the service, and keeps the lights safe. Before arming it checks
// every channel's duty cycle and thermal budget against its emitter's limits; armed, it goes dark when the
// controller's heartbeat stops; a blackout (the emergency stop) latches until reset; and it is dark on every path out.
#pragma once

#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/statusor.h"
#include "heartbeat_watch.h"
#include "stage/common/metrics.h"
#include "stage/light/light_driver.h"
#include "stage/light/slot_clock.h"
#include "stage/v1/light_node.pb.h"
#include "stage/v1/node.pb.h"
#include "stage/v1/rig.pb.h"

namespace stage::light {

struct LightNodeOptions {
  // The rig's slot clock, Hz, and the take length the thermal budget assumes when a take does not say, s.
  double slot_rate_hz = 912;
  double take_length_s = 10;
  // Armed without a heartbeat for this long, the node blacks out, ms (ArmLightRequest.heartbeat_timeout_ms overrides).
  int heartbeat_timeout_ms = 1000;
};

class LightNode {
 public:
  static absl::StatusOr<std::unique_ptr<LightNode>> Create(const v1::LightNodeConfig& config,
                                                           std::unique_ptr<LightDriver> driver, std::string rig_hash,
                                                           LightNodeOptions options = {});
  // Blacks out the driver: lights fail dark.
  ~LightNode();

  v1::NodeInfo Info() const;
  v1::LightStats Stats() const;
  // Checks the table against the channels' limits, loads it and arms (disarming first if armed); see LightNode.Arm in
  // light_node.proto. FailedPrecondition names the channel, its unit and the limit a table would exceed.
  absl::Status Arm(const v1::ArmLightRequest& request);
  absl::Status Disarm(const std::string& take_id);
  // Every channel dark, latched; `reason` is kept for the status.
  absl::Status Blackout(const std::string& reason);
  absl::Status ResetBlackout();
  // The controller is alive (feeds the watchdog while armed).
  void Heartbeat(const std::string& take_id);
  // Heartbeat losses that blacked the node out, since start.
  uint64_t watchdog_trips() const;

  // The slot clock this node drives (it is the rig's timing.sync_generator), in place of its driver's own (the gpiod
  // driver's clock output); set once, before serving.
  void SetSlotClock(std::unique_ptr<SlotClockGenerator> clock) {
    owned_slot_clock_ = std::move(clock);
    slot_clock_ = owned_slot_clock_.get();
  }
  bool drives_slot_clock() const { return slot_clock_ != nullptr; }
  // See LightNode.RunSlotClock, EndSlotClock and GetSlotClock. FailedPrecondition on a node without a slot clock.
  absl::StatusOr<v1::SlotClockRun> RunSlotClock(const v1::SlotClockRunRequest& request);
  absl::StatusOr<v1::SlotClockRun> EndSlotClock(int64_t align_slots);
  absl::StatusOr<v1::SlotClockRun> GetSlotClock();
  // See LightNode.StartTable and GetClockInput: a free-running clock's planned first edge, and the clock as seen.
  absl::Status StartTable(const std::string& take_id, int64_t first_edge_ns);
  absl::StatusOr<v1::ClockInput> ClockInput() const;

 private:
  LightNode(v1::LightNodeConfig config, std::unique_ptr<LightDriver> driver, std::string rig_hash,
            LightNodeOptions options);
  // The highest load of one channel of a table, of full drive: its mean (duty) and its thermal peak.
  struct TableLoad {
    double duty = 0;
    double peak = 0;
  };
  // FailedPrecondition when a channel would exceed its limits; `most` gets the highest loads checked.
  absl::Status CheckLoad(const PatternTable& table, int64_t take_slots, TableLoad* most) const;
  void CollectMetrics(metrics::Writer& w) const;
  absl::Status NoSlotClock() const;
  void Watchdog();

  v1::LightNodeConfig config_;
  std::unique_ptr<LightDriver> driver_;
  std::string rig_hash_;
  LightNodeOptions options_;

  std::mutex arm_mutex_;  // Arm one at a time
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;        // guarded by mutex_
  bool watching_ = false;        // armed by the controller: the watchdog runs; guarded by mutex_
  std::string take_id_;          // guarded by mutex_
  HeartbeatWatch heartbeat_;     // guarded by mutex_
  std::string blackout_reason_;  // guarded by mutex_
  uint64_t watchdog_trips_ = 0;  // guarded by mutex_
  TableLoad armed_load_;         // of the table armed last; guarded by mutex_
  std::thread watchdog_;
  std::unique_ptr<SlotClockGenerator> owned_slot_clock_;
  SlotClockGenerator* slot_clock_ = nullptr;  // owned_slot_clock_, or the driver's
  // The node's families for the metrics (last: the collector goes before what it reads).
  metrics::Registration metrics_;
};

}  // namespace stage::light
