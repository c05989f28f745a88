// Scheduled software triggers from the controller: one client stream per camera node, each trigger sent `lead` ahead
// of its time (timing.trigger_lead_slots) with its absolute controller time; the node fires it on its own clock.
// Triggers that fall due within a quarter of the lead are sent together, so a sender wakes a few times per lead, not
// once per slot; every trigger still leaves at least three quarters of the lead early. A node that fails delays only
// its own stream. Newer clock measurements go to the nodes during the take.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/timing/time_base.h"
#include "stage/v1/camera_node.pb.h"
#include "stage/v1/timing.pb.h"

namespace grpc {
class ClientContext;
}  // namespace grpc

namespace stage::controller {

struct TriggerTarget {
  std::string id;
  // host:port of the camera node.
  std::string address;
  // The camera's timing in the schedule (divider, phase, trigger offset, late slack).
  v1::CameraTiming timing;
  // Node clock against the controller's, as measured (ClockStatus); zero offset if unmeasured.
  v1::ClockMapping clock;
};

struct TriggerStreamOptions {
  std::string take_id;
  uint32_t slot_rate_hz = 912;
  // Controller time (Unix ns, CLOCK_REALTIME) of slot 0.
  int64_t t0_unix_ns = 0;
  int64_t first_slot = 0;
  int64_t slot_count = 0;
  // How far ahead triggers are sent; 0 sends each at its own time (a baseline that cannot work).
  int64_t lead_ns = 0;
  // Ask nodes for every trigger's lead in their reports (benchmarks).
  bool report_leads = false;
  // SCHED_FIFO priority for the nodes' firing threads (timing.trigger_realtime_priority).
  uint32_t realtime_priority = 0;
  // How long after the last trigger's time a stream may take to end (the node's report), ms.
  int64_t finish_timeout_ms = 10000;
  // Where newer clock measurements come from during the take (the controller's health monitor), by camera id; each
  // stream asks every `clock_update_interval_ns` and sends what changed. Null: the targets' mappings for the whole
  // take.
  std::function<std::optional<v1::ClockMapping>(const std::string& id)> clock_source;
  int64_t clock_update_interval_ns = 1'000'000'000;
};

class TriggerStreamer {
 public:
  TriggerStreamer(TriggerStreamOptions options, std::vector<TriggerTarget> targets);
  // Cancels whatever is still running.
  ~TriggerStreamer();

  // Starts one sender thread per target.
  void Start();
  // Waits for every stream to end; the node's report per target, in target order, or why that stream failed
  // (node unreachable, refused the stream).
  std::vector<absl::StatusOr<v1::TriggerReport>> Wait();
  // Ends every stream now: cancels the calls, so that a node that stopped answering cannot hold a sender. Safe from
  // any thread.
  void Cancel();

 private:
  void Send(size_t index);

  TriggerStreamOptions options_;
  std::vector<TriggerTarget> targets_;
  timing::TimeBase base_;
  std::vector<absl::StatusOr<v1::TriggerReport>> results_;
  std::vector<std::thread> threads_;
  // One call per target; each has a deadline past the take's last trigger plus finish_timeout_ms.
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts_;
  std::atomic<bool> cancelled_{false};
};

}  // namespace stage::controller
