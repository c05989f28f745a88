// The schedule compiler.
#include "stage/timing/schedule.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"

namespace stage::timing {
namespace {

const v1::LedLimits& UnitLimits(const v1::LightNodeConfig& node, const v1::LedUnit& unit) {
  return unit.has_limits() ? unit.limits() : node.unit_limits();
}

}  // namespace

double BytesPerPixel(v1::PixelFormat format) {
  switch (format) {
    case v1::PIXEL_FORMAT_MONO12:
    case v1::PIXEL_FORMAT_MONO16:
    case v1::PIXEL_FORMAT_BAYER_RG12:
    case v1::PIXEL_FORMAT_BAYER_RG16:
      return 2;
    case v1::PIXEL_FORMAT_RGB8:
      return 3;
    default:
      return 1;
  }
}

std::string ScheduleHash(const v1::Schedule& schedule) {
  v1::Schedule copy = schedule;
  copy.clear_hash();
  copy.clear_rig_hash();
  return StableHash(copy);
}

absl::StatusOr<v1::Schedule> CompileSchedule(const v1::RigConfig& rig, const PatternSet& patterns) {
  if (patterns.patterns.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("pattern set ", patterns.source, " has no patterns"));
  }
  const v1::TimingConfig& timing = rig.timing();
  STAGE_ASSIGN_OR_RETURN(TimeBase base, TimeBase::Create(static_cast<uint32_t>(timing.slot_rate_hz())));
  v1::Schedule schedule;
  schedule.set_pattern_set(patterns.name);
  *schedule.mutable_time_base() = base.ToProto();
  for (size_t i = 0; i < patterns.patterns.size(); ++i) {
    auto* p = schedule.add_patterns();
    p->set_index(static_cast<uint32_t>(i));
    p->set_name(patterns.patterns[i].name);
    p->set_polarization(patterns.patterns[i].polarization);
  }
  schedule.set_guard_ticks(base.UsToTicks(timing.exposure_guard_us()));
  schedule.set_take_slots(std::max<int64_t>(1, std::llround(timing.take_length_s() * timing.slot_rate_hz())));
  schedule.set_trigger_lead_slots(timing.trigger_lead_slots());
  const int64_t settle = base.UsToTicks(timing.led_settle_us());

  // Light nodes. Units are numbered across nodes in rig order, as RigUnits() lists them for the pattern set.
  size_t unit_index = 0;
  int64_t steady_start = 0;
  int64_t earliest_switch = std::numeric_limits<int64_t>::max();
  for (const v1::LightNodeConfig& node : rig.light_nodes()) {
    auto* n = schedule.add_light_nodes();
    n->set_id(node.id());
    const double switch_us = node.has_switch_delay_us() ? node.switch_delay_us() : timing.led_switch_delay_us();
    double rise_us = node.unit_limits().rise_us();
    double fall_us = node.unit_limits().fall_us();
    if (node.units_size() > 0) rise_us = fall_us = 0;
    for (const v1::LedUnit& unit : node.units()) {
      rise_us = std::max(rise_us, UnitLimits(node, unit).rise_us());
      fall_us = std::max(fall_us, UnitLimits(node, unit).fall_us());
    }
    n->set_switch_ticks(base.UsToTicks(switch_us));
    n->set_rise_ticks(base.UsToTicks(rise_us));
    n->set_fall_ticks(base.UsToTicks(fall_us));
    n->set_settle_ticks(settle);
    // Channels going up rise while channels going down fall; the light is steady once the slower has finished.
    n->set_steady_start_ticks(n->switch_ticks() + std::max(n->rise_ticks(), n->fall_ticks()) + settle);
    if (n->steady_start_ticks() > steady_start || schedule.steady_start_node().empty()) {
      steady_start = n->steady_start_ticks();
      schedule.set_steady_start_node(node.id());
    }
    if (n->switch_ticks() < earliest_switch) {
      earliest_switch = n->switch_ticks();
      schedule.set_steady_end_node(node.id());
    }

    v1::PatternTable* table = n->mutable_table();
    table->set_pattern_set(patterns.name);
    for (const Pattern& pattern : patterns.patterns) {
      v1::PatternRow* row = table->add_rows();
      row->set_name(pattern.name);
      std::vector<uint32_t> levels(node.channel_count(), 0);
      for (int u = 0; u < node.units_size(); ++u) {
        const v1::LedUnit& unit = node.units(u);
        const uint32_t channel =
            pattern.polarization == v1::POLARIZATION_PARALLEL ? unit.parallel_channel() : unit.cross_channel();
        const size_t w = unit_index + static_cast<size_t>(u);
        const double weight = w < pattern.weights.size() ? pattern.weights[w] : 0.0;
        if (channel < levels.size()) levels[channel] = static_cast<uint32_t>(std::lround(weight * 65535.0));
      }
      row->mutable_levels()->Assign(levels.begin(), levels.end());
    }
    unit_index += static_cast<size_t>(node.units_size());
  }
  if (rig.light_nodes_size() == 0) earliest_switch = 0;
  schedule.set_steady_start_ticks(steady_start);
  schedule.set_steady_end_ticks(base.ticks_per_slot() + earliest_switch);

  for (const v1::CameraConfig& camera : rig.cameras()) {
    auto* c = schedule.add_cameras();
    c->set_id(camera.id());
    c->set_role(camera.role());
    c->set_source(camera.trigger().source());
    c->set_divider(std::max<uint32_t>(1, camera.trigger().divider()));
    c->set_slot_phase(camera.trigger().slot_phase());
    c->set_trigger_auto(!camera.trigger().has_delay_us());
    c->set_trigger_ticks(c->trigger_auto() ? steady_start : base.UsToTicks(camera.trigger().delay_us()));
    c->set_exposure_ticks(base.UsToTicks(camera.exposure_us()));
    if (camera.trigger().source() == v1::TRIGGER_SOURCE_FREE_RUN && camera.frame_rate_hz() > 0) {
      c->set_period_ticks(base.NsToTicks(std::llround(1e9 / camera.frame_rate_hz())));
    } else {
      c->set_period_ticks(base.ticks_per_slot() * c->divider());
    }
    c->set_readout_declared(camera.readout_us() > 0);
    c->set_readout_ticks(c->readout_declared() ? base.UsToTicks(camera.readout_us())
                                               : std::max<int64_t>(0, c->period_ticks() - c->exposure_ticks()));
    c->set_overlap_exposure_readout(camera.overlap_exposure_readout());
    c->set_trigger_pulse_ticks(base.UsToTicks(timing.trigger_pulse_us()));
    c->set_frame_bytes(static_cast<int64_t>(
        std::llround(static_cast<double>(camera.width()) * camera.height() * BytesPerPixel(camera.pixel_format()))));
    c->set_early_slack_ticks(c->trigger_ticks() - steady_start);
    c->set_late_slack_ticks(schedule.steady_end_ticks() - schedule.guard_ticks() -
                            (c->trigger_ticks() + c->exposure_ticks()));
  }
  schedule.set_hash(ScheduleHash(schedule));
  schedule.set_rig_hash(RigHash(rig));
  return schedule;
}

int64_t NextFiringSlot(const v1::CameraTiming& camera, int64_t from) {
  const int64_t d = camera.divider() == 0 ? 1 : camera.divider();
  int64_t m = from % d;
  if (m < 0) m += d;
  int64_t delta = static_cast<int64_t>(camera.slot_phase()) - m;
  if (delta < 0) delta += d;
  return from + delta;
}

int64_t FiringsInTake(const v1::CameraTiming& camera, int64_t slots) {
  const int64_t d = camera.divider() == 0 ? 1 : camera.divider();
  const int64_t first = NextFiringSlot(camera, 0);
  return first < slots ? (slots - 1 - first) / d + 1 : 0;
}

v1::SlotEntry DescribeSlot(const v1::Schedule& schedule, int64_t slot) {
  const TimeBase base = TimeBase::FromProto(schedule.time_base());
  const int64_t n = CycleLength(schedule);
  int64_t p = slot % n;
  if (p < 0) p += n;
  v1::SlotEntry entry;
  entry.set_slot(slot);
  entry.set_start_ns(base.SlotStartNs(slot));
  entry.set_frame((slot - p) / n);
  entry.set_pattern(static_cast<uint32_t>(p));
  if (p < schedule.patterns_size()) {
    entry.set_pattern_name(schedule.patterns(static_cast<int>(p)).name());
    entry.set_polarization(schedule.patterns(static_cast<int>(p)).polarization());
  }
  for (const auto& c : schedule.cameras()) {
    if (FiresInSlot(c, slot)) entry.add_cameras(c.id());
  }
  return entry;
}

const v1::CameraTiming* FindCameraTiming(const v1::Schedule& schedule, const std::string& id) {
  for (const auto& c : schedule.cameras()) {
    if (c.id() == id) return &c;
  }
  return nullptr;
}

const v1::LightNodeTiming* FindLightTiming(const v1::Schedule& schedule, const std::string& id) {
  for (const auto& n : schedule.light_nodes()) {
    if (n.id() == id) return &n;
  }
  return nullptr;
}

}  // namespace stage::timing
