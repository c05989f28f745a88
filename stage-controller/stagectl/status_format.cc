// stagectl status output.
#include "status_format.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/node_info.h"
#include "stage/common/take_names.h"

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
  if (n.kind() == v1::NODE_KIND_CAMERA)
    return n.camera_role() == v1::CAMERA_ROLE_HIGH_SPEED ? "camera HS" : "camera MV";
  if (n.kind() == v1::NODE_KIND_PROCESSING_WORKER) return "worker";
  return NodeKindName(n.kind());
}

// "+3.001 ms ±12.4 us", "-" before the first measurement; a trailing " !" when the uncertainty is over the limit.
std::string FormatClock(const v1::ClockStatus& c) {
  if (!c.measured()) return c.flagged() ? "- !" : "-";
  auto time = [](int64_t ns, bool sign) {
    const double a = std::abs(static_cast<double>(ns));
    std::string s = sign ? (ns < 0 ? "-" : "+") : "";
    if (a < 1e6) return absl::StrCat(s, absl::StrFormat("%.1f us", a / 1e3));
    return absl::StrCat(s, absl::StrFormat("%.3f ms", a / 1e6));
  };
  return absl::StrCat(time(c.offset_ns(), true), " ±", time(c.uncertainty_ns(), false), c.flagged() ? " !" : "");
}

std::string FormatPtp(const v1::PtpStatus& p) {
  if (p.source().empty()) return "-";
  if (!p.error().empty()) return "error";
  return absl::StrFormat("%s %+.1f us", p.port_state(), p.master_offset_ns() / 1e3);
}

}  // namespace

std::string FormatStatusTable(const v1::StageStatus& status, int64_t now_unix_ns, bool color) {
  std::string out = absl::StrFormat("Stage %s (%s): %d of %d nodes up, session %s, controller %s\n\n",
                                    status.stage_id(), status.stage_name(), status.nodes_up(), status.nodes_total(),
                                    SessionStateName(status.session_state()), status.controller().version());
  if (!status.schedule_hash().empty()) {
    out.insert(
        out.size() - 1,
        absl::StrFormat("schedule %s: %d timing error(s), %d warning(s)%s\n", status.schedule_hash(),
                        status.timing_errors(), status.timing_warnings(),
                        status.timing_errors() + status.timing_warnings() > 0 ? " (stagectl timing check)" : ""));
  }
  if (status.estop_latched()) {
    out.insert(out.size() - 1, absl::StrFormat("EMERGENCY STOP LATCHED (%s): lights dark; `stagectl estop --reset` "
                                               "releases it\n",
                                               status.estop_reason()));
  }
  out += absl::StrFormat("%-18s %-10s %-22s %-12s %-8s %-8s %9s %10s %-22s %-16s  %s\n", "NODE", "KIND", "ADDRESS",
                         "STATE", "BACKEND", "VERSION", "RTT", "LAST SEEN", "CLOCK OFFSET", "PTP", "REASON");
  int flagged = 0;
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
    std::string reason = n.reason();
    if (n.clock().flagged()) {
      ++flagged;
      if (!reason.empty()) reason += "; ";
      if (n.clock().measured()) {
        absl::StrAppend(&reason,
                        absl::StrFormat("clock uncertainty %.1f us > %.1f us (%s)", n.clock().uncertainty_ns() / 1e3,
                                        n.clock().limit_ns() / 1e3, n.clock().limit_reason()));
      } else {
        absl::StrAppend(&reason, "clock not measured; its scheduled software triggers need it");
      }
    }
    out +=
        absl::StrFormat("%-18s %-10s %-22s %s %-8s %-8s %9s %10s %-22s %-16s  %s\n", n.id(), KindLabel(n), n.address(),
                        padded, n.backend().empty() ? "-" : n.backend(), n.version().empty() ? "-" : n.version(), rtt,
                        seen, FormatClock(n.clock()), FormatPtp(n.clock().ptp()), reason);
  }
  if (flagged > 0) {
    out += absl::StrFormat("\n%d node%s flagged (!): clock uncertainty beyond what the trigger mode tolerates.\n",
                           flagged, flagged == 1 ? " is" : "s are");
  }
  int down = status.nodes_total() - status.nodes_up();
  if (down > 0) {
    out += absl::StrFormat("\n%d node%s not up.\n", down, down == 1 ? " is" : "s are");
  }
  return out;
}

}  // namespace stage::stagectl
