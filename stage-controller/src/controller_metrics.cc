// The controller's metrics (controller_metrics.h).
#include "controller_metrics.h"

#include "capture.h"
#include "health_monitor.h"
#include "stage/common/node_info.h"
#include "stage/common/take_names.h"

namespace stage::controller {

metrics::Registration CollectNodeHealth(const HealthMonitor* monitor, metrics::Registry& registry) {
  return registry.AddCollector([monitor](metrics::Writer& w) {
    for (const v1::NodeStatus& n : monitor->Snapshot()) {
      const metrics::Labels node = {{"node", n.id()}, {"kind", NodeKindName(n.kind())}};
      for (v1::NodeState s :
           {v1::NODE_STATE_UNKNOWN, v1::NODE_STATE_UP, v1::NODE_STATE_DOWN, v1::NODE_STATE_UNREACHABLE}) {
        metrics::Labels labels = node;
        labels.emplace_back("state", NodeStateName(s));
        w.Gauge("stage_node_state", "The node's health as the controller polls it: 1 for its state, 0 for the others",
                labels, NodeStateName(n.state()) == NodeStateName(s) ? 1 : 0);
      }
      if (n.state() == v1::NODE_STATE_UP) {
        w.Gauge("stage_node_health_rtt_seconds", "Round trip of the node's last health check", node,
                static_cast<double>(n.rtt_ns()) * 1e-9);
      }
      const v1::ClockStatus& clock = n.clock();
      if (!clock.measured()) continue;
      w.Gauge("stage_node_clock_offset_seconds", "The node's clock minus the controller's (NodeClock.Sync)", node,
              static_cast<double>(clock.offset_ns()) * 1e-9);
      w.Gauge("stage_node_clock_uncertainty_seconds", "Bound on the error of the node's measured clock offset", node,
              static_cast<double>(clock.uncertainty_ns()) * 1e-9);
      w.Gauge("stage_node_clock_flagged",
              "1 when the node's clock uncertainty exceeds what its trigger mode tolerates, else 0", node,
              clock.flagged() ? 1 : 0);
    }
  });
}

metrics::Registration CollectSessionState(const Capturer* capturer, metrics::Registry& registry) {
  return registry.AddCollector([capturer](metrics::Writer& w) {
    const v1::SessionState now = capturer->state();
    for (int s = v1::SessionState_MIN; s <= v1::SessionState_MAX; ++s) {
      if (!v1::SessionState_IsValid(s) || s == v1::SESSION_STATE_UNSPECIFIED) continue;
      w.Gauge("stage_session_state", "The capture session's state: 1 for the current one, 0 for the others",
              {{"state", SessionStateName(static_cast<v1::SessionState>(s))}}, s == now ? 1 : 0);
    }
  });
}

void CountTake(v1::TakeState state, int64_t frames_expected, int64_t frames_stored, metrics::Registry& registry) {
  registry
      .GetCounter("stage_takes_total", "Takes kept in the catalog, by their state", {{"state", TakeStateName(state)}})
      ->Increment();
  registry.GetCounter("stage_take_frames_expected_total", "Frames the kept takes expected (every camera, every slot)")
      ->Increment(static_cast<double>(frames_expected));
  registry.GetCounter("stage_take_frames_stored_total", "Frames the kept takes stored")
      ->Increment(static_cast<double>(frames_stored));
}

}  // namespace stage::controller
