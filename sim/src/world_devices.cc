// Simulated devices in the world.
#include "stage/sim/world_devices.h"

#include <cmath>
#include <set>

#include "absl/strings/str_cat.h"
#include "stage/common/status.h"
#include "stage/timing/schedule.h"

namespace stage::sim {

light::PatternTable TableFromSchedule(const v1::LightNodeTiming& timing) {
  light::PatternTable table;
  table.pattern_set = timing.table().pattern_set();
  for (const v1::PatternRow& row : timing.table().rows()) {
    table.row_names.push_back(row.name());
    light::ChannelLevels levels;
    levels.reserve(static_cast<size_t>(row.levels_size()));
    for (uint32_t l : row.levels()) levels.push_back(static_cast<uint16_t>(std::min<uint32_t>(l, 65535)));
    table.rows.push_back(std::move(levels));
  }
  return table;
}

absl::StatusOr<NodeWorld> OpenNodeWorld(const LoadedRig& loaded, const std::string& address) {
  NodeWorld out;
  STAGE_ASSIGN_OR_RETURN(out.scene, SimScene::FromLoadedRig(loaded));
  STAGE_ASSIGN_OR_RETURN(out.client, ConnectWorld(address));
  return out;
}

absl::Status JoinLightNode(SimLightDriver* driver, const SimScene& scene, const std::string& node_id,
                           WorldClient* world, std::function<void()> on_crash, bool arm,
                           std::function<void(int64_t)> on_edge) {
  const int index = scene.LightNodeIndex(node_id);
  if (index < 0 || index >= scene.schedule().light_nodes_size()) {
    return absl::NotFoundError(absl::StrCat("light node \"", node_id, "\" is not in the rig"));
  }
  if (arm) {
    STAGE_RETURN_IF_ERROR(driver->LoadPatternTable(TableFromSchedule(scene.schedule().light_nodes(index))));
    STAGE_RETURN_IF_ERROR(driver->Arm());
  }
  SimLightWorld w;
  w.world = world;
  w.node_index = index;
  w.switch_delay_ns = scene.SwitchDelayNs(index);
  const v1::SimFault fault = scene.Fault(node_id);
  const v1::LightNodeConfig& config = scene.rig().light_nodes(index);
  w.extra_delay_ns = static_cast<int64_t>(std::llround((config.has_sim() ? config.sim().extra_delay_us() : 0) * 1e3));
  w.fault_delay_ns = static_cast<int64_t>(std::llround(fault.delay_us() * 1e3));
  if (fault.has_crash_at_s()) w.crash_at_ns = static_cast<int64_t>(std::llround(fault.crash_at_s() * 1e9));
  w.on_crash = std::move(on_crash);
  w.on_edge = std::move(on_edge);
  return driver->AttachWorld(w);
}

absl::StatusOr<SimCameraWorld> CameraWorld(std::shared_ptr<const SimScene> scene, const std::string& camera_id,
                                           WorldClient* world) {
  const int index = scene->CameraIndex(camera_id);
  if (index < 0 || index >= scene->schedule().cameras_size()) {
    return absl::NotFoundError(absl::StrCat("camera \"", camera_id, "\" is not in the rig"));
  }
  const v1::CameraTiming& t = scene->schedule().cameras(index);
  const timing::TimeBase& base = scene->base();
  SimCameraWorld w;
  w.world = world;
  w.divider = t.divider() == 0 ? 1 : t.divider();
  w.phase = t.slot_phase();
  w.trigger_delay_ns = base.TicksToNs(t.trigger_ticks());
  w.exposure_ns = base.TicksToNs(t.exposure_ticks());
  w.cycle_slots = timing::CycleLength(scene->schedule());
  const v1::SimFault fault = scene->Fault(camera_id);
  w.miss_triggers = fault.miss_triggers();
  w.drop_frames = fault.drop_frames();
  w.drop_slots = {fault.drop_slots().begin(), fault.drop_slots().end()};
  w.clock_offset_ns = static_cast<int64_t>(std::llround(fault.clock_offset_us() * 1000));
  w.clock_drift_ppm = fault.clock_drift_ppm();
  if (fault.has_crash_at_s()) w.crash_at_ns = static_cast<int64_t>(std::llround(fault.crash_at_s() * 1e9));
  w.seed = scene->rig().sim().seed();
  // The patterns the camera's slots show (a machine-vision camera: its full-on one): the renderer sums each pose's
  // responses under them alone, unless a mistimed or faulty exposure brings others (CameraRenderer::ExpectOnly).
  std::set<int64_t> patterns;
  const int64_t cycle_patterns = std::max(1, scene->schedule().patterns_size());
  for (int64_t slot = 0; slot < w.cycle_slots * w.divider; ++slot) {  // every phase of the divider against the cycle
    if (timing::FiresInSlot(t, slot)) patterns.insert(slot % cycle_patterns);
  }
  std::vector<EmitterLevels> exposures;
  for (const int64_t p : patterns) exposures.push_back(scene->PatternLevels(static_cast<int>(p)));
  w.renderer = std::make_shared<CameraRenderer>(std::move(scene), index);
  w.renderer->ExpectOnly(std::move(exposures));
  return w;
}

void ApplyUnitFaults(const SimScene& scene, World* world) {
  const auto& units = scene.dome().units;
  for (size_t u = 0; u < units.size(); ++u) {
    const v1::SimFault fault = scene.Fault(units[u].id);
    if (fault.dead() || fault.delay_us() != 0) {
      world->SetUnitFault(u, {fault.dead(), static_cast<int64_t>(std::llround(fault.delay_us() * 1000))});
    }
  }
}

}  // namespace stage::sim
