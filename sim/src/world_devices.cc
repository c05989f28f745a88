// Simulated devices in the world.
#include "stage/sim/world_devices.h"

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

absl::Status JoinLightNode(SimLightDriver* driver, const SimScene& scene, const std::string& node_id,
                           WorldClient* world, int64_t extra_delay_ns) {
  const int index = scene.LightNodeIndex(node_id);
  if (index < 0 || index >= scene.schedule().light_nodes_size()) {
    return absl::NotFoundError(absl::StrCat("light node \"", node_id, "\" is not in the rig"));
  }
  STAGE_RETURN_IF_ERROR(driver->LoadPatternTable(TableFromSchedule(scene.schedule().light_nodes(index))));
  STAGE_RETURN_IF_ERROR(driver->Arm());
  SimLightWorld w;
  w.world = world;
  w.node_index = index;
  w.switch_delay_ns = scene.SwitchDelayNs(index);
  w.extra_delay_ns = extra_delay_ns;
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
  w.renderer = std::make_shared<CameraRenderer>(std::move(scene), index);
  return w;
}

}  // namespace stage::sim
