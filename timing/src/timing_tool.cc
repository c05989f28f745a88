// Timing checks and exports on a rig, and their text.
#include "stage/timing/timing_tool.h"

#include <google/protobuf/util/json_util.h>

#include <map>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/status.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"
#include "stage/timing/verifier.h"
#include "stage/timing/waveform.h"

namespace stage::timing {
namespace {

std::string Us(const TimeBase& base, int64_t ticks) { return absl::StrFormat("%.3f", base.TicksToUs(ticks)); }

std::string SourceName(v1::TriggerSource source) {
  switch (source) {
    case v1::TRIGGER_SOURCE_HARDWARE_LINE:
      return "line";
    case v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE:
      return "scheduled";
    case v1::TRIGGER_SOURCE_FREE_RUN:
      return "free-run";
    default:
      return "?";
  }
}

}  // namespace

absl::StatusOr<v1::TimingReport> CheckTiming(const LoadedRig& rig, const v1::TimingQuery& query) {
  std::vector<std::string> overrides(query.overrides().begin(), query.overrides().end());
  STAGE_ASSIGN_OR_RETURN(LoadedRig effective, ApplyRigOverrides(rig, overrides));
  return CheckRigTiming(effective.rig, effective.base_dir);
}

absl::StatusOr<v1::TimingExport> ExportTiming(const LoadedRig& rig, const v1::TimingExportRequest& request) {
  v1::TimingQuery query;
  *query.mutable_overrides() = request.overrides();
  STAGE_ASSIGN_OR_RETURN(v1::TimingReport report, CheckTiming(rig, query));
  WaveformWindow window;
  window.first_slot = request.first_slot();
  window.slot_count = request.slot_count() > 0 ? request.slot_count() : CycleLength(report.schedule());
  if (window.first_slot < 0) {
    return absl::InvalidArgumentError(absl::StrCat("first slot ", window.first_slot, " is negative"));
  }
  const TimeBase base = TimeBase::FromProto(report.schedule().time_base());
  if (window.first_slot > base.max_slot() - window.slot_count) {
    return absl::InvalidArgumentError(
        absl::StrFormat("slots %d to %d are beyond the exact time base (up to slot %d, %.0f days at %u slots/s)",
                        window.first_slot, window.first_slot + window.slot_count - 1, base.max_slot(),
                        static_cast<double>(base.max_slot()) / base.slot_rate_hz() / 86400, base.slot_rate_hz()));
  }
  if (window.slot_count > kMaxExportSlots) {
    return absl::InvalidArgumentError(
        absl::StrCat("a window of ", window.slot_count, " slots is too long to export; at most ", kMaxExportSlots));
  }
  VcdOptions vcd_options;
  if (!request.timescale().empty()) {
    STAGE_ASSIGN_OR_RETURN(vcd_options.timescale_fs, ParseTimescale(request.timescale()));
  }
  v1::TimingExport out;
  out.set_first_slot(window.first_slot);
  out.set_slot_count(window.slot_count);
  if (request.vcd()) {
    STAGE_ASSIGN_OR_RETURN(*out.mutable_vcd(), ScheduleToVcd(report.schedule(), window, vcd_options));
  }
  if (request.svg()) {
    STAGE_ASSIGN_OR_RETURN(*out.mutable_svg(), ReportToSvg(report, window));
  }
  if (request.json()) {
    v1::ScheduleExport e;
    *e.mutable_report() = report;
    e.set_first_slot(window.first_slot);
    e.set_slot_count(window.slot_count);
    for (int64_t k = window.first_slot; k < window.first_slot + window.slot_count; ++k) {
      *e.add_slots() = DescribeSlot(report.schedule(), k);
    }
    google::protobuf::util::JsonPrintOptions options;
    options.add_whitespace = true;
    options.preserve_proto_field_names = true;
    auto s = google::protobuf::util::MessageToJsonString(e, out.mutable_json(), options);
    if (!s.ok()) return absl::InternalError(absl::StrCat("JSON export: ", s.message().as_string()));
  }
  *out.mutable_report() = std::move(report);
  return out;
}

std::string FormatViolations(const v1::TimingReport& report, absl::string_view rig_name) {
  const v1::Schedule& s = report.schedule();
  std::string out = absl::StrFormat("schedule %s: %s, %d patterns at %u slots/s, from %s\n", s.hash(), s.pattern_set(),
                                    s.patterns_size(), s.time_base().slot_rate_hz(), rig_name);
  for (const v1::Violation& v : report.violations()) {
    absl::StrAppend(&out, absl::StrFormat("%-7s %-15s %s%s: %s\n", SeverityName(v.severity()), v.check(), v.device(),
                                          v.slot() >= 0 ? absl::StrCat(" slot ", v.slot()) : "", v.message()));
    absl::StrAppend(&out, absl::StrFormat("%-23s fix: %s\n", "", v.fix()));
  }
  absl::StrAppend(&out, absl::StrFormat("%d error(s), %d warning(s): %s\n", report.errors(), report.warnings(),
                                        report.errors() > 0 ? "nothing arms until the errors are fixed"
                                                            : "the schedule may be armed"));
  return out;
}

std::string FormatScheduleSummary(const v1::TimingReport& report, absl::string_view rig_name) {
  const v1::Schedule& s = report.schedule();
  const TimeBase base = TimeBase::FromProto(s.time_base());
  const int64_t n = CycleLength(s);
  std::map<std::string, const v1::LoadFigure*> link, ram, led;
  for (const auto& f : report.loads()) {
    if (f.kind() == "link") link[f.device()] = &f;
    if (f.kind() == "ram") ram[f.device()] = &f;
    if (f.kind() == "led") led[f.device()] = &f;
  }
  std::string out;
  absl::StrAppend(&out, absl::StrFormat("schedule %s from %s\n", s.hash(), rig_name));
  absl::StrAppend(&out, absl::StrFormat("  pattern set %s: %d patterns; slot %s us (%u Hz); cycle %d slots = %s us "
                                        "(%.6g Hz); take %d slots = %.3f s\n",
                                        s.pattern_set(), s.patterns_size(), Us(base, base.ticks_per_slot()),
                                        s.time_base().slot_rate_hz(), n, Us(base, n * base.ticks_per_slot()),
                                        static_cast<double>(s.time_base().slot_rate_hz()) / n, s.take_slots(),
                                        static_cast<double>(s.take_slots()) / s.time_base().slot_rate_hz()));
  absl::StrAppend(
      &out, absl::StrFormat("  light steady from %s us (%s) until the next switch at %s us (%s), less the "
                            "guard of %s us\n",
                            Us(base, s.steady_start_ticks()), s.steady_start_node(), Us(base, s.steady_end_ticks()),
                            s.steady_end_node(), Us(base, s.guard_ticks())));
  absl::StrAppend(&out, absl::StrFormat("  exact time: 1 tick = 1/%d s (%d ticks per ns, %d per slot)\n\n",
                                        s.time_base().ticks_per_second(), s.time_base().ticks_per_ns(),
                                        s.time_base().ticks_per_slot()));

  absl::StrAppend(&out, absl::StrFormat("%-18s %10s %8s %8s %9s %12s %8s %14s\n", "LIGHT NODE", "SWITCH us", "RISE us",
                                        "FALL us", "SETTLE us", "STEADY FROM", "CHANNELS", "HOTTEST/LIMIT"));
  for (const auto& node : s.light_nodes()) {
    auto it = led.find(node.id());
    std::string hottest =
        it == led.end() ? "-" : absl::StrFormat("%.3f/%.2f", it->second->used(), it->second->budget());
    const int channels = node.table().rows_size() > 0 ? node.table().rows(0).levels_size() : 0;
    absl::StrAppend(
        &out, absl::StrFormat("%-18s %10s %8s %8s %9s %12s %8d %14s\n", node.id(), Us(base, node.switch_ticks()),
                              Us(base, node.rise_ticks()), Us(base, node.fall_ticks()), Us(base, node.settle_ticks()),
                              Us(base, node.steady_start_ticks()), channels, hottest));
  }
  absl::StrAppend(&out, "\n");
  absl::StrAppend(
      &out, absl::StrFormat("%-8s %-4s %-9s %5s %-19s %11s %11s %11s %17s %s\n", "CAMERA", "ROLE", "SOURCE", "EVERY",
                            "PHASE", "TRIGGER us", "EXPOSURE us", "READOUT us", "SLACK early/late", "LOAD"));
  for (const auto& c : s.cameras()) {
    const std::string phase =
        absl::StrCat(c.slot_phase(), " ",
                     c.slot_phase() < static_cast<uint32_t>(s.patterns_size()) && c.divider() % n == 0
                         ? s.patterns(static_cast<int>(c.slot_phase())).name()
                         : "");
    std::string load;
    if (auto it = link.find(c.id()); it != link.end()) {
      load = absl::StrFormat("link %.1f/%.0f MB/s", it->second->used(), it->second->budget());
    } else if (auto r = ram.find(c.id()); r != ram.end()) {
      load = absl::StrFormat("RAM %.1f/%.0f GiB", r->second->used(), r->second->budget());
    }
    absl::StrAppend(
        &out, absl::StrFormat(
                  "%-8s %-4s %-9s %5d %-19s %11s %11s %11s %17s %s\n", c.id(),
                  c.role() == v1::CAMERA_ROLE_HIGH_SPEED ? "hs" : "mv", SourceName(c.source()), c.divider(), phase,
                  absl::StrCat(Us(base, c.trigger_ticks()), c.trigger_auto() ? "*" : ""), Us(base, c.exposure_ticks()),
                  absl::StrCat(Us(base, c.readout_ticks()), c.readout_declared() ? "" : "~"),
                  absl::StrCat(Us(base, c.early_slack_ticks()), "/", Us(base, c.late_slack_ticks())), load));
  }
  absl::StrAppend(&out,
                  "  * trigger follows the light (trigger.delay_us unset)   ~ readout assumed: rest of the period\n");
  std::string disks;
  for (const auto& f : report.loads()) {
    if (f.kind() == "disk")
      absl::StrAppend(&disks, absl::StrFormat("  %s %.1f/%.0f MB/s", f.device(), f.used(), f.budget()));
  }
  if (!disks.empty()) absl::StrAppend(&out, "\nrecording hosts:", disks, "\n");
  if (report.flicker_size() > 0) {
    absl::StrAppend(&out, "flicker at the performer's eyes:");
    for (const auto& f : report.flicker()) {
      absl::StrAppend(&out, absl::StrFormat("  %.4g Hz %.2f %% (line %.2f %%)", f.frequency_hz(), f.modulation() * 100,
                                            f.warn_modulation() * 100));
    }
    absl::StrAppend(&out, "\n");
  }
  absl::StrAppend(&out, absl::StrFormat("verifier: %d error(s), %d warning(s)%s\n", report.errors(), report.warnings(),
                                        report.violations_size() > 0 ? " (stagectl timing check lists them)" : ""));
  return out;
}

}  // namespace stage::timing
