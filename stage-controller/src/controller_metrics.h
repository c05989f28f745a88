// The controller's Prometheus metrics (docs/operators.md#metrics): every node's health and clock as the controller
// measures them, the session's state, and the takes it has kept.
#pragma once

#include "stage/common/metrics.h"
#include "stage/v1/take.pb.h"

namespace stage::controller {

class HealthMonitor;
class Capturer;

// Node health and clock families, read from `monitor` at each scrape (it must outlive the registration):
// stage_node_state{node,kind,state} (1 for the node's state, 0 for the others), stage_node_health_rtt_seconds,
// stage_node_clock_offset_seconds and _uncertainty_seconds (measured nodes), stage_node_clock_flagged.
[[nodiscard]] metrics::Registration CollectNodeHealth(const HealthMonitor* monitor,
                                                      metrics::Registry& registry = metrics::Registry::Default());

// stage_session_state{state}: 1 for the session's state, 0 for the others; read from `capturer`.
[[nodiscard]] metrics::Registration CollectSessionState(const Capturer* capturer,
                                                        metrics::Registry& registry = metrics::Registry::Default());

// A kept take: stage_takes_total{state}, stage_take_frames_expected_total, stage_take_frames_stored_total.
void CountTake(v1::TakeState state, int64_t frames_expected, int64_t frames_stored,
               metrics::Registry& registry = metrics::Registry::Default());

}  // namespace stage::controller
