// The schedule verifier.
#include "stage/timing/verifier.h"

#include <algorithm>
#include <cmath>
#include <complex>
#include <map>
#include <set>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/timing/led_load.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"

namespace stage::timing {
namespace {

constexpr double kMB = 1e6;
constexpr double kGiB = 1024.0 * 1024.0 * 1024.0;
constexpr double kMiB = 1024.0 * 1024.0;
// Below this frequency a modulation of the total light counts as flicker for the performer (the photosensitive
// band; IEEE 1789-2015 treats < 90 Hz separately too).
constexpr double kFlickerBandHz = 60.0;
// Budgets used above this fraction draw a warning: no headroom for packet resends or a slow disk.
constexpr double kHeadroomFraction = 0.9;
// A scheduled software trigger fires with the jitter of a non-real-time thread; less slack than this warns.
constexpr double kSoftwareTriggerJitterUs = 100.0;
// Less lead than this for scheduled software triggers warns: a loaded network has millisecond tails.
constexpr double kMinTriggerLeadMs = 2.0;

// The rig file's spelling of an enum value: "PIXEL_FORMAT_BAYER_RG8" -> "bayer-rg8".
std::string YamlName(const std::string& full, absl::string_view prefix) {
  std::string name = absl::StartsWith(full, prefix) ? full.substr(prefix.size()) : full;
  for (char& ch : name) ch = ch == '_' ? '-' : absl::ascii_tolower(static_cast<unsigned char>(ch));
  return name;
}

std::string PixelFormatYaml(v1::PixelFormat f) { return YamlName(v1::PixelFormat_Name(f), "PIXEL_FORMAT_"); }

std::string LinkLabel(v1::LinkKind link) {
  switch (link) {
    case v1::LINK_KIND_GIGE_1:
      return "a 1 GigE link";
    case v1::LINK_KIND_GIGE_2_5:
      return "a 2.5 GigE link";
    case v1::LINK_KIND_GIGE_5:
      return "a 5 GigE link";
    case v1::LINK_KIND_GIGE_10:
      return "a 10 GigE link";
    case v1::LINK_KIND_USB3:
      return "USB3";
    case v1::LINK_KIND_COAXPRESS_12:
      return "a CoaXPress-12 link";
    default:
      return YamlName(v1::LinkKind_Name(link), "LINK_KIND_");
  }
}

// One way to fix a violation: in words, and as the rig overrides that make it. It is offered only if the verifier, run
// again on the rig with those overrides, no longer finds the violation and finds no error it did not find before.
struct Remedy {
  std::string words;
  std::vector<std::string> overrides;
};

class Report {
 public:
  explicit Report(v1::TimingReport* report) : report_(report) {}
  void Add(v1::Severity severity, absl::string_view check, const std::string& device, int64_t slot, std::string message,
           std::string fix) {
    Add(severity, check, device, slot, std::move(message), {}, std::move(fix));
  }
  // `remedies` are tried (VerifySchedule) before they go into the fix, ahead of `other_fix` (advice that is no single
  // setting, in words). `kind` tells this violation from others of the same check and device (a frame-rate warning
  // from a frame-rate error): a remedy fixes it when no violation of the same kind remains.
  void Add(v1::Severity severity, absl::string_view check, const std::string& device, int64_t slot, std::string message,
           std::vector<Remedy> remedies, std::string other_fix, std::string kind = "") {
    if (!remedies.empty()) pending_.push_back({report_->violations_size(), std::move(remedies), other_fix});
    kinds_.push_back(std::move(kind));
    v1::Violation* v = report_->add_violations();
    v->set_severity(severity);
    v->set_check(std::string(check));
    v->set_device(device);
    v->set_slot(slot);
    v->set_message(std::move(message));
    v->set_fix(std::move(other_fix));  // remedies join it once tried
    if (severity == v1::SEVERITY_ERROR) {
      report_->set_errors(report_->errors() + 1);
    } else {
      report_->set_warnings(report_->warnings() + 1);
    }
  }
  void Error(absl::string_view check, const std::string& device, int64_t slot, std::string message, std::string fix) {
    Add(v1::SEVERITY_ERROR, check, device, slot, std::move(message), std::move(fix));
  }
  void Warning(absl::string_view check, const std::string& device, int64_t slot, std::string message, std::string fix) {
    Add(v1::SEVERITY_WARNING, check, device, slot, std::move(message), std::move(fix));
  }
  // A violation's remedies, waiting to be tried.
  struct Pending {
    int violation;
    std::vector<Remedy> remedies;
    std::string other_fix;
  };
  const std::vector<Pending>& pending() const { return pending_; }
  const std::string& kind(int violation) const { return kinds_[static_cast<size_t>(violation)]; }
  void Load(absl::string_view kind, const std::string& device, double used, double budget, absl::string_view unit) {
    v1::LoadFigure* f = report_->add_loads();
    f->set_kind(std::string(kind));
    f->set_device(device);
    f->set_used(used);
    f->set_budget(budget);
    f->set_unit(std::string(unit));
  }
  v1::TimingReport* proto() { return report_; }

 private:
  v1::TimingReport* report_;
  std::vector<Pending> pending_;
  std::vector<std::string> kinds_;  // per violation
};

// Context shared by the checks.
struct Ctx {
  const v1::RigConfig& rig;
  const PatternSet& patterns;
  const v1::Schedule& schedule;
  TimeBase base;
  Report& out;

  std::string Us(int64_t ticks) const { return absl::StrFormat("%.3f", base.TicksToUs(ticks)); }
  double SlotUs() const { return base.TicksToUs(base.ticks_per_slot()); }
  std::string PatternOf(int64_t slot) const {
    const int64_t n = CycleLength(schedule);
    int64_t p = slot % n;
    if (p < 0) p += n;
    return p < schedule.patterns_size() ? schedule.patterns(static_cast<int>(p)).name() : "?";
  }
  std::string SlotLabel(int64_t slot) const { return absl::StrCat("slot ", slot, " (", PatternOf(slot), ")"); }
};

// ---- the rig as a whole: can a take run at all --------------------------------------------------------------------

void CheckRig(Ctx& ctx) {
  if (ctx.rig.cameras_size() == 0) {
    ctx.out.Error(kCheckRig, "cameras", -1, "the rig has no camera: a take would record nothing",
                  "add the stage's cameras under `cameras` (docs/configuration.md#cameras)");
  }
  if (ctx.rig.light_nodes_size() == 0) {
    ctx.out.Error(kCheckRig, "light_nodes", -1,
                  "the rig has no light node: no pattern would be shown and nothing would light the subject",
                  "add the stage's LED controllers under `light_nodes` (docs/configuration.md#light_nodes)");
  }
}

// ---- light nodes: is there a steady window at all ----------------------------------------------------------------

void CheckSlotTiming(Ctx& ctx) {
  const int64_t slot = ctx.base.ticks_per_slot();
  for (const v1::LightNodeTiming& n : ctx.schedule.light_nodes()) {
    if (n.switch_ticks() >= slot) {
      ctx.out.Error(kCheckSlotTiming, n.id(), 0,
                    absl::StrCat("switch delay ", ctx.Us(n.switch_ticks()), " us is not shorter than the slot (",
                                 ctx.Us(slot), " us): the node would show each pattern in the next slot"),
                    absl::StrCat("set light_nodes[", n.id(), "].switch_delay_us (or timing.led_switch_delay_us) below ",
                                 ctx.Us(slot), " us"));
    } else if (n.steady_start_ticks() >= slot + n.switch_ticks()) {
      ctx.out.Error(kCheckSlotTiming, n.id(), 0,
                    absl::StrCat("the light never settles: switch ", ctx.Us(n.switch_ticks()), " + rise/fall ",
                                 ctx.Us(std::max(n.rise_ticks(), n.fall_ticks())), " + settle ",
                                 ctx.Us(n.settle_ticks()), " us = ", ctx.Us(n.steady_start_ticks()),
                                 " us reaches the next switch at ", ctx.Us(slot + n.switch_ticks()), " us"),
                    "shorten timing.led_settle_us, or use faster emitters, or lower timing.slot_rate_hz");
    }
  }
}

// ---- cameras ------------------------------------------------------------------------------------------------------

void CheckSteadyLight(Ctx& ctx, const v1::CameraConfig& config, const v1::CameraTiming& c) {
  if (ctx.schedule.light_nodes_size() == 0) return;
  if (c.source() == v1::TRIGGER_SOURCE_FREE_RUN) return;  // not locked to slots: the frame-rate check warns
  const int64_t slot = NextFiringSlot(c, 0);
  const int64_t start = c.trigger_ticks();
  const int64_t end = c.trigger_ticks() + c.exposure_ticks();
  const int64_t steady = ctx.schedule.steady_start_ticks();
  const int64_t last_end = ctx.schedule.steady_end_ticks() - ctx.schedule.guard_ticks();
  const v1::LightNodeTiming* first = FindLightTiming(ctx.schedule, ctx.schedule.steady_start_node());
  const v1::LightNodeTiming* last = FindLightTiming(ctx.schedule, ctx.schedule.steady_end_node());
  if (start < steady && first != nullptr) {
    ctx.out.Error(
        kCheckSteadyLight, c.id(), slot,
        absl::StrCat("exposure starts at ", ctx.Us(start), " us after the edge of ", ctx.SlotLabel(slot),
                     ", before the light is steady at ", ctx.Us(steady), " us (light node ", first->id(), ": switch ",
                     ctx.Us(first->switch_ticks()), " + rise/fall ",
                     ctx.Us(std::max(first->rise_ticks(), first->fall_ticks())), " + settle ",
                     ctx.Us(first->settle_ticks()), " us): it blends the previous pattern into the image"),
        absl::StrCat("set cameras[", c.id(), "].trigger.delay_us >= ", ctx.Us(steady),
                     " (or leave it unset to follow the light), or shorten the LED switch delay or settle time"));
  }
  if (end > last_end && last != nullptr) {
    const int64_t max_exposure = last_end - start;
    ctx.out.Error(kCheckSteadyLight, c.id(), slot,
                  absl::StrCat("exposure ends at ", ctx.Us(end), " us after the edge of ", ctx.SlotLabel(slot), ", ",
                               ctx.Us(end - last_end), " us after the last moment it may: ", ctx.Us(last_end),
                               " us = next slot edge ", ctx.Us(ctx.base.ticks_per_slot()), " + switch of ", last->id(),
                               " ", ctx.Us(last->switch_ticks()), " - exposure_guard ",
                               ctx.Us(ctx.schedule.guard_ticks()), " us: it blends the next pattern into the image"),
                  max_exposure > 0
                      ? absl::StrCat("shorten cameras[", c.id(), "].exposure_us to <= ", ctx.Us(max_exposure),
                                     " (trigger at ", ctx.Us(start), " us)")
                      : absl::StrCat("trigger cameras[", c.id(), "] earlier (trigger.delay_us)"));
  }
}

void CheckFrameRate(Ctx& ctx, const v1::CameraConfig& config, const v1::CameraTiming& c) {
  const double rate = static_cast<double>(ctx.base.ticks_per_second()) / static_cast<double>(c.period_ticks());
  const int64_t slot = NextFiringSlot(c, 0);
  if (c.source() == v1::TRIGGER_SOURCE_FREE_RUN) {
    ctx.out.Warning(kCheckFrameRate, c.id(), -1,
                    absl::StrFormat("free-running at %g fps: the exposure phase drifts against the slot clock with "
                                    "the camera's oscillator, so frames are not locked to patterns",
                                    config.frame_rate_hz()),
                    "use trigger.source hardware-line or scheduled-software for pattern-locked frames");
  } else if (std::abs(config.frame_rate_hz() - rate) > 1e-6 * rate) {
    const auto divider =
        static_cast<uint32_t>(std::max(1.0, std::round(ctx.base.slot_rate_hz() / config.frame_rate_hz())));
    ctx.out.Add(
        v1::SEVERITY_WARNING, kCheckFrameRate, c.id(), slot,
        absl::StrFormat("frame_rate_hz is %g but the schedule triggers it every %d slot(s) = %.6g Hz; the camera's "
                        "acquisition frame rate setting will not match its triggers",
                        config.frame_rate_hz(), c.divider(), rate),
        {{absl::StrFormat("set cameras[%s].frame_rate_hz: %.6g", c.id(), rate),
          {absl::StrFormat("cameras[%s].frame_rate_hz=%.17g", c.id(), rate)}},
         {absl::StrFormat("set cameras[%s].trigger.divider: %u", c.id(), divider),
          {absl::StrFormat("cameras[%s].trigger.divider=%u", c.id(), divider)}}},
        "", "rate mismatch");
  }
  if (config.max_frame_rate_hz() > 0 && rate > config.max_frame_rate_hz() * (1 + 1e-9)) {
    const auto min_divider =
        static_cast<uint32_t>(std::ceil(ctx.base.slot_rate_hz() / config.max_frame_rate_hz() - 1e-9));
    // The smallest divider that is fast enough and keeps the camera on its pattern (a divisor or multiple of the
    // cycle), with its frame rate to match.
    const auto cycle = static_cast<uint32_t>(CycleLength(ctx.schedule));
    uint32_t divider = min_divider;
    while (cycle > 0 && divider % cycle != 0 && cycle % divider != 0) ++divider;
    const double new_rate = ctx.base.slot_rate_hz() / divider;
    ctx.out.Add(
        v1::SEVERITY_ERROR, kCheckFrameRate, c.id(), slot,
        absl::StrFormat("triggered at %.6g Hz, but at %ux%u %s it reaches at most %g fps "
                        "(max_frame_rate_hz)",
                        rate, config.width(), config.height(), PixelFormatYaml(config.pixel_format()),
                        config.max_frame_rate_hz()),
        {{absl::StrFormat("set cameras[%s].trigger.divider: %u (and frame_rate_hz: %.6g)", c.id(), divider, new_rate),
          {absl::StrFormat("cameras[%s].trigger.divider=%u", c.id(), divider),
           absl::StrFormat("cameras[%s].trigger.slot_phase=%u", c.id(), c.slot_phase() % divider),
           absl::StrFormat("cameras[%s].frame_rate_hz=%.17g", c.id(), new_rate)}}},
        "reduce the ROI (height)", "above the camera's maximum");
  }
  if (c.readout_declared() && c.readout_ticks() > c.period_ticks()) {
    ctx.out.Error(kCheckFrameRate, c.id(), slot,
                  absl::StrCat("readout ", ctx.Us(c.readout_ticks()), " us is longer than the trigger period ",
                               ctx.Us(c.period_ticks()), " us: readouts queue up and frames are lost"),
                  absl::StrCat("raise cameras[", c.id(), "].trigger.divider, or reduce the ROI to shorten readout"));
  }
}

void CheckPatternLock(Ctx& ctx, const v1::CameraConfig& config, const v1::CameraTiming& c) {
  if (c.source() == v1::TRIGGER_SOURCE_FREE_RUN) return;  // not locked to slots: the frame-rate check warns
  const auto cycle = static_cast<uint32_t>(CycleLength(ctx.schedule));
  const uint32_t d = std::max<uint32_t>(1, c.divider());
  if (cycle == 0 || d % cycle == 0 || cycle % d == 0) return;
  // The pattern under its trigger moves from one cycle to the next: frames of the same camera are lit differently.
  const int64_t first = NextFiringSlot(c, 0);
  std::vector<std::string> seen;
  for (int k = 0; k < 3; ++k) seen.push_back(ctx.SlotLabel(first + k * static_cast<int64_t>(d)));
  std::vector<uint32_t> near;  // the dividers next to it that keep it on its pattern
  for (uint32_t m = std::max<uint32_t>(1, d - 1); m > 0 && near.empty(); --m) {
    if (m % cycle == 0 || cycle % m == 0) near.push_back(m);
  }
  near.push_back((d / cycle + 1) * cycle);
  ctx.out.Error(kCheckPatternLock, c.id(), first,
                absl::StrFormat("triggered every %u slots against a cycle of %u patterns, it fires on a different "
                                "pattern each time (%s, ...): its frames are lit by different patterns",
                                d, cycle, absl::StrJoin(seen, ", ")),
                absl::StrFormat("set cameras[%s].trigger.divider to a divisor or a multiple of %u (e.g. %s)",
                                config.id(), cycle, absl::StrJoin(near, " or ")));
}

void CheckTriggerOverlap(Ctx& ctx, const v1::CameraConfig& config, const v1::CameraTiming& c) {
  const int64_t slot = NextFiringSlot(c, 0);
  const int64_t next = slot + c.divider();
  if (c.trigger_pulse_ticks() >= c.period_ticks()) {
    ctx.out.Error(kCheckTriggerOverlap, c.id(), slot,
                  absl::StrCat("trigger pulse ", ctx.Us(c.trigger_pulse_ticks()), " us is not shorter than the ",
                               "trigger period ", ctx.Us(c.period_ticks()), " us: the line never returns low"),
                  absl::StrCat("set timing.trigger_pulse_us below ", ctx.Us(c.period_ticks() / 2)));
  }
  if (!c.overlap_exposure_readout()) {
    const int64_t busy = c.exposure_ticks() + c.readout_ticks();
    if (busy > c.period_ticks()) {
      ctx.out.Error(
          kCheckTriggerOverlap, c.id(), next,
          absl::StrCat("the trigger of slot ", next, " comes ", ctx.Us(c.period_ticks() - c.exposure_ticks()),
                       " us into the readout of slot ", slot, " (exposure ", ctx.Us(c.exposure_ticks()), " + readout ",
                       ctx.Us(c.readout_ticks()), " = ", ctx.Us(busy), " us > trigger period ",
                       ctx.Us(c.period_ticks()),
                       " us); without overlapped exposure the camera ignores it and every second frame is lost"),
          absl::StrCat("enable overlapped exposure (cameras[", c.id(),
                       "].overlap_exposure_readout: true, TriggerOverlap=ReadOut) if the sensor has it, shorten "
                       "exposure_us to <= ",
                       ctx.Us(std::max<int64_t>(0, c.period_ticks() - c.readout_ticks())),
                       ", or raise trigger.divider"));
    }
  } else if (c.exposure_ticks() > c.period_ticks()) {
    ctx.out.Error(kCheckTriggerOverlap, c.id(), next,
                  absl::StrCat("the trigger of slot ", next, " arrives during the exposure of slot ", slot,
                               " (exposure ", ctx.Us(c.exposure_ticks()), " us > trigger period ",
                               ctx.Us(c.period_ticks()), " us); the camera ignores it"),
                  absl::StrCat("shorten cameras[", c.id(), "].exposure_us below ", ctx.Us(c.period_ticks()),
                               " or raise trigger.divider"));
  }
}

void CheckTriggerLead(Ctx& ctx, const v1::CameraTiming& c) {
  if (c.source() != v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE) return;
  const double lead_ms = ctx.schedule.trigger_lead_slots() * ctx.SlotUs() / 1000.0;
  if (lead_ms < kMinTriggerLeadMs) {
    ctx.out.Warning(kCheckTriggerLead, c.id(), -1,
                    absl::StrFormat("scheduled triggers are sent %u slot(s) = %.3f ms ahead; gRPC over a loaded "
                                    "network has millisecond tails, and a trigger that arrives late is missed",
                                    ctx.schedule.trigger_lead_slots(), lead_ms),
                    absl::StrFormat("raise timing.trigger_lead_slots to >= %.0f",
                                    std::ceil(kMinTriggerLeadMs * 1000.0 / ctx.SlotUs())));
  }
  const double slack_us = ctx.base.TicksToUs(c.late_slack_ticks());
  if (c.late_slack_ticks() >= 0 && slack_us < kSoftwareTriggerJitterUs) {
    ctx.out.Warning(kCheckTriggerLead, c.id(), NextFiringSlot(c, 0),
                    absl::StrFormat("a scheduled software trigger may fire only %.3f us late before the exposure "
                                    "leaves the steady light; a software timer on Linux is often %.0f us late",
                                    slack_us, kSoftwareTriggerJitterUs),
                    absl::StrCat("shorten cameras[", c.id(), "].exposure_us, or trigger it by hardware line"));
  }
}

void CheckLink(Ctx& ctx, const v1::CameraConfig& config, const v1::CameraTiming& c) {
  const double budget = LinkBudgetBytesPerSecond(config.link());
  if (budget <= 0) return;
  const bool gige = config.link() == v1::LINK_KIND_GIGE_1 || config.link() == v1::LINK_KIND_GIGE_2_5 ||
                    config.link() == v1::LINK_KIND_GIGE_5 || config.link() == v1::LINK_KIND_GIGE_10;
  const double rate = static_cast<double>(ctx.base.ticks_per_second()) / static_cast<double>(c.period_ticks());
  const double frame = static_cast<double>(c.frame_bytes());
  const double wire_frame = gige ? GigeWireBytesPerFrame(frame, config.packet_size()) : frame;
  const double payload = frame * rate;
  const double wire = wire_frame * rate;
  const std::string link = LinkLabel(config.link());
  ctx.out.Load("link", c.id(), wire / kMB, budget / kMB, "MB/s");
  const std::string what = absl::StrFormat(
      "%.1f MB/s of frames (%ux%u %s at %.6g fps) needs %.1f MB/s on the link%s; %s carries %.1f MB/s", payload / kMB,
      config.width(), config.height(), PixelFormatYaml(config.pixel_format()), rate, wire / kMB,
      gige ? absl::StrFormat(" with GVSP/UDP/IP/Ethernet overhead at packet size %u", config.packet_size()) : "", link,
      budget / kMB);
  if (wire <= budget) {
    if (wire > kHeadroomFraction * budget) {
      ctx.out.Warning(kCheckLinkBandwidth, c.id(), -1,
                      absl::StrCat(what, ": less than 10% headroom for resent packets"),
                      "use a faster link, jumbo frames (packet_size 9000) or a smaller ROI");
    }
    return;
  }
  // How many rows fit, for the fix.
  const double rows_fit = std::floor(config.height() * budget / wire);
  std::string fix = absl::StrFormat(
      "use a faster link (2.5/5/10 GigE), reduce the ROI to <= %.0f rows, or lower the "
      "frame rate",
      rows_fit);
  if (gige && config.packet_size() < 9000) {
    const double jumbo = GigeWireBytesPerFrame(frame, 9000) * rate;
    absl::StrAppend(&fix, absl::StrFormat(jumbo <= budget ? "; jumbo frames (packet_size 9000: %.1f MB/s) also fit"
                                                          : "; jumbo frames (packet_size 9000: %.1f MB/s) are not "
                                                            "enough",
                                          jumbo / kMB));
  }
  // The backlog a take leaves, in frame bytes.
  const double take_s = ctx.rig.timing().take_length_s();
  const double backlog = (wire - budget) / wire * payload * take_s;
  const double buffer = config.frame_buffer_mib() * kMiB;
  if (buffer <= 0) {
    ctx.out.Warning(kCheckLinkBandwidth, c.id(), -1,
                    absl::StrFormat("%s: frames are lost unless the camera buffers the backlog, %.0f MiB by the end "
                                    "of a %g s take (frame_buffer_mib not declared)",
                                    what, backlog / kMiB, take_s),
                    fix);
  } else if (backlog > buffer) {
    const double overflow_s = buffer / ((wire - budget) / wire * payload);
    ctx.out.Error(kCheckLinkBandwidth, c.id(), -1,
                  absl::StrFormat("%s: the %g MiB frame buffer overflows %.2f s into the take (backlog %.0f MiB by "
                                  "the end of %g s); frames after that are lost",
                                  what, config.frame_buffer_mib(), overflow_s, backlog / kMiB, take_s),
                  fix);
  } else {
    ctx.out.Warning(
        kCheckLinkBandwidth, c.id(), -1,
        absl::StrFormat("%s: the %g MiB frame buffer absorbs the %.0f MiB backlog of a %g s take; the "
                        "last frames arrive %.2f s after the take",
                        what, config.frame_buffer_mib(), backlog / kMiB, take_s, backlog * (wire / payload) / budget),
        fix);
  }
}

void CheckCameraRam(Ctx& ctx, const v1::CameraConfig& config, const v1::CameraTiming& c) {
  if (config.link() != v1::LINK_KIND_ON_CAMERA_RAM) return;
  const int64_t take = ctx.schedule.take_slots();
  // Slot-locked cameras fire in the slots their divider and phase pick; a free-running one once per its own period.
  const int64_t frames = c.source() == v1::TRIGGER_SOURCE_FREE_RUN
                             ? (take * ctx.base.ticks_per_slot() + c.period_ticks() - 1) / c.period_ticks()
                             : (take - NextFiringSlot(c, 0) + c.divider() - 1) / c.divider();
  const double bytes = static_cast<double>(frames) * static_cast<double>(c.frame_bytes());
  const double ram = config.ram_gib() * kGiB;
  ctx.out.Load("ram", c.id(), bytes / kGiB, config.ram_gib(), "GiB");
  if (bytes <= ram) return;
  const double rate = static_cast<double>(ctx.base.ticks_per_second()) / static_cast<double>(c.period_ticks());
  const double frames_fit = std::floor(ram / static_cast<double>(c.frame_bytes()));
  const double seconds_fit = frames_fit / rate;
  const int64_t last_slot = NextFiringSlot(c, 0) + static_cast<int64_t>(frames_fit) * c.divider();
  ctx.out.Error(kCheckCameraRam, c.id(), last_slot,
                absl::StrFormat("a %g s take is %d frames x %.2f MB = %.1f GiB; on-camera RAM holds %g GiB = %.0f "
                                "frames = %.2f s, so recording stops at slot %d",
                                ctx.rig.timing().take_length_s(), frames, c.frame_bytes() / kMB, bytes / kGiB,
                                config.ram_gib(), frames_fit, seconds_fit, last_slot),
                absl::StrFormat("shorten timing.take_length_s to <= %.2f s, reduce the ROI, or raise "
                                "cameras[%s].trigger.divider",
                                seconds_fit, c.id()));
}

void CheckDisks(Ctx& ctx) {
  // Live recording only: on-camera RAM is offloaded after the take.
  std::map<std::string, std::pair<double, std::vector<std::string>>> hosts;
  for (int i = 0; i < ctx.rig.cameras_size(); ++i) {
    const v1::CameraConfig& config = ctx.rig.cameras(i);
    if (config.link() == v1::LINK_KIND_ON_CAMERA_RAM) continue;
    const v1::CameraTiming& c = ctx.schedule.cameras(i);
    const double rate = static_cast<double>(ctx.base.ticks_per_second()) / static_cast<double>(c.period_ticks());
    auto& h = hosts[config.recording_host()];
    h.first += static_cast<double>(c.frame_bytes()) * rate;
    h.second.push_back(c.id());
  }
  const double budget = ctx.rig.storage().host_write_mb_per_s() * kMB;
  for (const auto& [host, load] : hosts) {
    ctx.out.Load("disk", host, load.first / kMB, budget / kMB, "MB/s");
    const std::string what = absl::StrFormat(
        "recording host %s writes %.1f MB/s for %d camera(s) (%s); its store sustains %g MB/s", host, load.first / kMB,
        load.second.size(), absl::StrJoin(load.second, ", "), ctx.rig.storage().host_write_mb_per_s());
    if (load.first > budget) {
      ctx.out.Error(kCheckDiskWrite, host, -1, what + ": frames back up in memory and are lost",
                    "move cameras to another recording_host, or raise storage.host_write_mb_per_s if the disks "
                    "really sustain more (measure it)");
    } else if (load.first > kHeadroomFraction * budget) {
      ctx.out.Warning(kCheckDiskWrite, host, -1, what + ": less than 10% headroom",
                      "move a camera to another recording_host");
    }
  }
}

// ---- LED channels -------------------------------------------------------------------------------------------------

struct ChannelInfo {
  std::string unit;
  const char* emitter = "";
  const v1::LedLimits* limits = nullptr;
};

void CheckLeds(Ctx& ctx) {
  const double slot_s = 1.0 / ctx.base.slot_rate_hz();
  const int64_t take = ctx.schedule.take_slots();
  for (int ni = 0; ni < ctx.rig.light_nodes_size(); ++ni) {
    const v1::LightNodeConfig& node = ctx.rig.light_nodes(ni);
    const v1::LightNodeTiming& timing = ctx.schedule.light_nodes(ni);
    std::vector<ChannelInfo> channels(node.channel_count());
    for (const v1::LedUnit& u : node.units()) {
      const v1::LedLimits* limits = u.has_limits() ? &u.limits() : &node.unit_limits();
      if (u.parallel_channel() < channels.size()) channels[u.parallel_channel()] = {u.id(), "parallel", limits};
      if (u.cross_channel() < channels.size()) channels[u.cross_channel()] = {u.id(), "cross", limits};
    }
    const int rows = timing.table().rows_size();
    if (rows == 0) continue;
    int duty_over = 0, thermal_over = 0;
    double worst_duty = -1, worst_thermal = -1, hottest = 0, hottest_limit = 1;
    uint32_t worst_duty_ch = 0, worst_thermal_ch = 0;
    for (uint32_t ch = 0; ch < channels.size(); ++ch) {
      const ChannelInfo& info = channels[ch];
      if (info.limits == nullptr) continue;  // no emitter on this channel
      std::vector<double> u(rows);
      for (int r = 0; r < rows; ++r) {
        const auto& levels = timing.table().rows(r).levels();
        u[r] = ch < static_cast<uint32_t>(levels.size()) ? levels[static_cast<int>(ch)] / 65535.0 : 0.0;
      }
      const LedLoad load = ComputeLedLoad(u, slot_s, info.limits->thermal_time_constant_s(), take);
      const double duty = load.duty;
      const double peak = load.peak;
      const double limit = info.limits->max_duty_cycle();
      if (peak / limit > hottest / hottest_limit) {
        hottest = peak;
        hottest_limit = limit;
      }
      if (duty > limit + 1e-12) {
        ++duty_over;
        if (duty - limit > worst_duty) {
          worst_duty = duty - limit;
          worst_duty_ch = ch;
        }
      } else if (peak > limit + 1e-12) {
        ++thermal_over;
        if (peak - limit > worst_thermal) {
          worst_thermal = peak - limit;
          worst_thermal_ch = ch;
        }
      }
    }
    ctx.out.Load("led", node.id(), hottest, hottest_limit, "duty");
    auto label = [&](uint32_t ch) {
      return absl::StrCat(node.id(), "/ch", ch, " (", channels[ch].unit, " ", channels[ch].emitter, ")");
    };
    if (duty_over > 0) {
      const ChannelInfo& info = channels[worst_duty_ch];
      const double limit = info.limits->max_duty_cycle();
      ctx.out.Error(kCheckLedDuty, absl::StrCat(node.id(), "/ch", worst_duty_ch), -1,
                    absl::StrFormat("%d channel(s) of %s run above their duty limit; the worst, %s, averages %.3f of "
                                    "full drive over the %d-pattern cycle, limit max_duty_cycle %g",
                                    duty_over, node.id(), label(worst_duty_ch), limit + worst_duty, rows, limit),
                    "lower the pattern levels on these emitters, or raise max_duty_cycle only if the emitter's data "
                    "sheet allows it");
    }
    if (thermal_over > 0) {
      const ChannelInfo& info = channels[worst_thermal_ch];
      const double limit = info.limits->max_duty_cycle();
      ctx.out.Error(kCheckLedThermal, absl::StrCat(node.id(), "/ch", worst_thermal_ch), -1,
                    absl::StrFormat("%d channel(s) of %s exceed their thermal budget; the worst, %s, reaches a load of "
                                    "%.3f of full drive (first-order model, thermal_time_constant_s %g) during a "
                                    "%g s take, limit max_duty_cycle %g",
                                    thermal_over, node.id(), label(worst_thermal_ch), limit + worst_thermal,
                                    info.limits->thermal_time_constant_s(), ctx.rig.timing().take_length_s(), limit),
                    "spread the bright patterns of these emitters over the cycle, lower their levels, or improve "
                    "the heat sink (a longer thermal_time_constant_s)");
    }
  }
}

// ---- flicker ------------------------------------------------------------------------------------------------------

void CheckFlicker(Ctx& ctx) {
  // Light reaching the performer's eyes from each LED unit, per slot of the cycle: the emitter's level times the
  // unit's calibration times the cosine of its direction to the gaze (+z, towards the front cameras); units behind
  // the face plane do not reach the eyes. Cross and parallel emitters both count: the eye has no analyzer.
  const int rows = static_cast<int>(CycleLength(ctx.schedule));
  std::vector<double> total(rows, 0.0);
  for (int ni = 0; ni < ctx.rig.light_nodes_size(); ++ni) {
    const v1::LightNodeConfig& node = ctx.rig.light_nodes(ni);
    const v1::PatternTable& table = ctx.schedule.light_nodes(ni).table();
    for (const v1::LedUnit& u : node.units()) {
      const auto& d = u.direction();
      const double len = std::sqrt(d.x() * d.x() + d.y() * d.y() + d.z() * d.z());
      const double w = len > 0 ? std::max(0.0, d.z() / len) * u.intensity_scale() : 0.0;
      if (w == 0) continue;
      for (int r = 0; r < rows && r < table.rows_size(); ++r) {
        const auto& levels = table.rows(r).levels();
        for (uint32_t ch : {u.parallel_channel(), u.cross_channel()}) {
          if (ch < static_cast<uint32_t>(levels.size())) total[r] += w * levels[static_cast<int>(ch)] / 65535.0;
        }
      }
    }
  }
  double mean = 0;
  for (double v : total) mean += v;
  mean /= rows;
  if (!(mean > 0)) return;
  const double rate = ctx.base.slot_rate_hz();
  for (int h = 1; h <= rows / 2; ++h) {
    const double f = h * rate / rows;
    if (f >= kFlickerBandHz) break;
    std::complex<double> c = 0;
    for (int k = 0; k < rows; ++k) c += total[k] * std::polar(1.0, -2.0 * M_PI * h * k / rows);
    c /= static_cast<double>(rows);
    const double modulation = (h * 2 == rows ? 1.0 : 2.0) * std::abs(c) / mean;
    const double warn =
        ctx.rig.timing().flicker_warn_modulation() > 0 ? ctx.rig.timing().flicker_warn_modulation() : 0.00025 * f;
    const double error = ctx.rig.timing().flicker_error_modulation();
    v1::FlickerComponent* component = ctx.out.proto()->add_flicker();
    component->set_frequency_hz(f);
    component->set_modulation(modulation);
    component->set_warn_modulation(warn);
    const std::string what = absl::StrFormat(
        "the total light reaching the performer's eyes is modulated by %.2f %% at %.4g Hz (the %d-slot pattern "
        "cycle's harmonic %d), %s",
        modulation * 100, f, rows, h,
        modulation > error
            ? absl::StrFormat("above the error line %.2f %% (timing.flicker_error_modulation)", error * 100)
            : absl::StrFormat("above the warning line %.2f %% (%s)", warn * 100,
                              ctx.rig.timing().flicker_warn_modulation() > 0
                                  ? "timing.flicker_warn_modulation"
                                  : "IEEE 1789-2015 low-risk: 0.025 % x f below 90 Hz"));
    const std::string fix =
        "reorder the patterns so that bright and dim ones alternate within the cycle (the shipped fastage-38 order "
        "cancels its 48 Hz component), or give the polarization blocks the same order";
    if (modulation > error) {
      ctx.out.Error(kCheckFlicker, "performer", -1, what, fix);
    } else if (modulation > warn) {
      ctx.out.Warning(kCheckFlicker, "performer", -1, what, fix);
    }
  }
}

// Every check once; the violations' remedies are left in `out` untried.
void RunChecks(const v1::RigConfig& rig, const PatternSet& patterns, const v1::Schedule& schedule, Report& out) {
  Ctx ctx{rig, patterns, schedule, TimeBase::FromProto(schedule.time_base()), out};
  CheckRig(ctx);
  CheckSlotTiming(ctx);
  for (int i = 0; i < rig.cameras_size() && i < schedule.cameras_size(); ++i) {
    const v1::CameraConfig& config = rig.cameras(i);
    const v1::CameraTiming& c = schedule.cameras(i);
    CheckSteadyLight(ctx, config, c);
    CheckFrameRate(ctx, config, c);
    CheckPatternLock(ctx, config, c);
    CheckTriggerOverlap(ctx, config, c);
    CheckTriggerLead(ctx, c);
    CheckLink(ctx, config, c);
    CheckCameraRam(ctx, config, c);
  }
  CheckDisks(ctx);
  CheckLeds(ctx);
  CheckFlicker(ctx);
}

// What a remedy is judged against, found once per rig: its validation errors (paths relative to the rig file resolve
// the same wrong way with a remedy as without, so only new ones count) and the checks that failed it as errors.
struct RemedyBaseline {
  RemedyBaseline(const v1::RigConfig& rig, const v1::TimingReport& report) {
    for (const RigError& e : ValidateRig(rig, "")) invalid.insert(e.path + ": " + e.message);
    for (const v1::Violation& v : report.violations()) {
      if (v.severity() == v1::SEVERITY_ERROR) errors.insert({v.check(), v.device()});
    }
  }
  std::set<std::string> invalid;                         // "path: message"
  std::set<std::pair<std::string, std::string>> errors;  // (check, device)
};

// Whether `remedy` fixes violation `index` of `before` (the rig's; `kinds` its violations' kinds): the rig with its
// overrides is no less valid, compiles, and the verifier no longer finds that violation (of that kind), nor any error
// it did not find before.
bool RemedyWorks(const v1::RigConfig& rig, const PatternSet& patterns, const RemedyBaseline& baseline,
                 const v1::TimingReport& before, const Report& kinds, int index, const Remedy& remedy) {
  v1::RigConfig changed = rig;
  for (const std::string& o : remedy.overrides) {
    if (!ApplyRigOverride(&changed, o).ok()) return false;
  }
  ApplyRigDefaults(&changed);
  for (const RigError& e : ValidateRig(changed, "")) {
    if (!baseline.invalid.count(e.path + ": " + e.message)) return false;
  }
  auto schedule = CompileSchedule(changed, patterns);
  if (!schedule.ok()) return false;
  v1::TimingReport after;
  Report out(&after);
  RunChecks(changed, patterns, *schedule, out);
  const v1::Violation& v = before.violations(index);
  for (int i = 0; i < after.violations_size(); ++i) {
    const v1::Violation& a = after.violations(i);
    if (a.check() == v.check() && a.device() == v.device() && out.kind(i) == kinds.kind(index)) return false;
    if (a.severity() == v1::SEVERITY_ERROR && !baseline.errors.count({a.check(), a.device()})) return false;
  }
  return true;
}

}  // namespace

double LinkBudgetBytesPerSecond(v1::LinkKind link) {
  switch (link) {
    case v1::LINK_KIND_GIGE_1:
      return 125e6;
    case v1::LINK_KIND_GIGE_2_5:
      return 312.5e6;
    case v1::LINK_KIND_GIGE_5:
      return 625e6;
    case v1::LINK_KIND_GIGE_10:
      return 1250e6;
    case v1::LINK_KIND_USB3:
      // 5 Gbit/s with 8b/10b coding is 500 MB/s; USB3 Vision bulk transfers reach about 400 MB/s of payload.
      return 400e6;
    case v1::LINK_KIND_COAXPRESS_12:
      // CXP-12: 12.5 Gbit/s with 8b/10b coding, about 1200 MB/s of payload per link.
      return 1200e6;
    default:
      return 0;
  }
}

double GigeWireBytesPerFrame(double frame_bytes, uint32_t packet_size) {
  // IP (20) + UDP (8) + GVSP (8) headers inside the packet; Ethernet header (14), FCS (4), preamble and start
  // delimiter (8) and the inter-frame gap (12) around it. A leader and a trailer packet per frame (~ 100 bytes on
  // the wire each).
  const double payload = static_cast<double>(packet_size) - 36.0;
  const double packets = std::ceil(frame_bytes / payload);
  return packets * (packet_size + 38.0) + 2 * 100.0;
}

absl::string_view SeverityName(v1::Severity severity) {
  return severity == v1::SEVERITY_ERROR ? "error" : severity == v1::SEVERITY_WARNING ? "warning" : "?";
}

v1::TimingReport VerifySchedule(const v1::RigConfig& rig, const PatternSet& patterns, const v1::Schedule& schedule) {
  v1::TimingReport report;
  *report.mutable_schedule() = schedule;
  Report out(&report);
  RunChecks(rig, patterns, schedule, out);
  // Every concrete setting a fix proposes is checked before it is offered: one that would not fix the violation (it
  // is already so), or that would break something else, is left out.
  const RemedyBaseline baseline(rig, report);
  for (const Report::Pending& p : out.pending()) {
    v1::Violation* v = report.mutable_violations(p.violation);
    std::vector<std::string> offered;
    for (const Remedy& r : p.remedies) {
      if (RemedyWorks(rig, patterns, baseline, report, out, p.violation, r)) offered.push_back(r.words);
    }
    if (!p.other_fix.empty()) offered.push_back(p.other_fix);
    v->set_fix(offered.empty() ? "no single setting found that fixes it without breaking another check"
                               : absl::StrJoin(offered, ", or "));
  }
  return report;
}

absl::StatusOr<v1::TimingReport> CheckRigTiming(const v1::RigConfig& rig, absl::string_view base_dir) {
  STAGE_ASSIGN_OR_RETURN(PatternSet patterns, LoadRigPatternSet(rig, base_dir));
  STAGE_ASSIGN_OR_RETURN(v1::Schedule schedule, CompileSchedule(rig, patterns));
  return VerifySchedule(rig, patterns, schedule);
}

}  // namespace stage::timing
