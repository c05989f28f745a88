// stagectl status output.
#include "status_format.h"

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/node_info.h"

namespace stage::stagectl {
namespace {

std::string FormatDuration(int64_t ns) {
  if (ns < 0) ns = 0;
  double s = ns / 1e9;
  if (s < 1) return absl::StrFormat("%.0f ms", s * 1000);
  if (s < 120) return absl::StrFormat("%.1f s", s);
  if (s < 7200) return absl::StrFormat("%.0f min", s / 60);
  return absl::StrFormat("%.1f h", s / 3600);
}

std::string KindLabel(const v1::NodeStatus& n) {
  if (n.kind() == v1::NODE_KIND_CAMERA) return n.role() == "high-speed" ? "camera HS" : "camera MV";
  if (n.kind() == v1::NODE_KIND_PROCESSING_WORKER) return "worker";
  return NodeKindName(n.kind());
}

}  // namespace

std::string FormatStatusTable(const v1::StageStatus& status, int64_t now_unix_ns, bool color) {
  std::string out = absl::StrFormat("Stage %s (%s): %d of %d nodes up, session %s, controller %s\n\n",
                                    status.stage_id(), status.stage_name(), status.nodes_up(), status.nodes_total(),
                                    status.session_state(), status.controller().version());
  if (!status.schedule_hash().empty()) {
    out.insert(out.size() - 1, absl::StrFormat("schedule %s: %d timing error(s), %d warning(s)%s\n",
                                               status.schedule_hash(), status.timing_errors(),
                                               status.timing_warnings(),
                                               status.timing_errors() + status.timing_warnings() > 0
                                                   ? " (stagectl timing check)"
                                                   : ""));
  }
  out += absl::StrFormat("%-18s %-10s %-22s %-12s %-8s %-8s %9s %10s  %s\n", "NODE", "KIND", "ADDRESS", "STATE",
                         "BACKEND", "VERSION", "RTT", "LAST SEEN", "REASON");
  for (const v1::NodeStatus& n : status.nodes()) {
    std::string state = NodeStateName(n.state());
    std::string padded = absl::StrFormat("%-12s", state);
    if (color) {
      const char* code = n.state() == v1::NODE_STATE_UP        ? "\033[32m"
                         : n.state() == v1::NODE_STATE_UNKNOWN ? "\033[33m"
                                                               : "\033[31m";
      padded = absl::StrCat(code, state, "\033[0m", std::string(12 > state.size() ? 12 - state.size() : 0, ' '));
    }
    std::string rtt = n.rtt_ns() > 0 ? absl::StrFormat("%.2f ms", n.rtt_ns() / 1e6) : "-";
    std::string seen =
        n.last_seen_unix_ns() > 0 ? FormatDuration(now_unix_ns - n.last_seen_unix_ns()) + " ago" : "never";
    out += absl::StrFormat("%-18s %-10s %-22s %s %-8s %-8s %9s %10s  %s\n", n.id(), KindLabel(n), n.address(), padded,
                           n.backend().empty() ? "-" : n.backend(), n.version().empty() ? "-" : n.version(), rtt, seen,
                           n.reason());
  }
  int down = status.nodes_total() - status.nodes_up();
  if (down > 0) {
    out += absl::StrFormat("\n%d node%s not up.\n", down, down == 1 ? " is" : "s are");
  }
  return out;
}

std::string StatusToJson(const v1::StageStatus& status) {
  nlohmann::ordered_json j;
  j["stage"] = {{"id", status.stage_id()}, {"name", status.stage_name()}};
  j["time_unix_ns"] = status.time_unix_ns();
  j["session_state"] = status.session_state();
  j["controller"] = {{"version", status.controller().version()},
                     {"pid", status.controller().pid()},
                     {"hostname", status.controller().hostname()},
                     {"uptime_ns", status.controller().uptime_ns()},
                     {"rig_hash", status.controller().rig_hash()}};
  j["summary"] = {{"nodes_up", status.nodes_up()}, {"nodes_total", status.nodes_total()}};
  j["timing"] = {{"schedule_hash", status.schedule_hash()},
                 {"errors", status.timing_errors()},
                 {"warnings", status.timing_warnings()}};
  nlohmann::ordered_json nodes = nlohmann::ordered_json::array();
  for (const v1::NodeStatus& n : status.nodes()) {
    nodes.push_back({{"id", n.id()},
                     {"kind", NodeKindName(n.kind())},
                     {"role", n.role()},
                     {"address", n.address()},
                     {"state", NodeStateName(n.state())},
                     {"reason", n.reason()},
                     {"version", n.version()},
                     {"backend", n.backend()},
                     {"pid", n.pid()},
                     {"uptime_ns", n.uptime_ns()},
                     {"last_seen_unix_ns", n.last_seen_unix_ns()},
                     {"rtt_ns", n.rtt_ns()},
                     {"state_since_unix_ns", n.state_since_unix_ns()}});
  }
  j["nodes"] = std::move(nodes);
  return j.dump(2);
}

}  // namespace stage::stagectl
