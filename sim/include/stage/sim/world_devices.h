// Wiring the rig's simulated devices into the world: a light node's table from the compiled schedule, a camera's
// trigger plan and renderer. Used by the node programs (with --sim-world) and by in-process tests of the whole stage.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/light/light_driver.h"
#include "stage/sim/scene.h"
#include "stage/sim/sim_camera_device.h"
#include "stage/sim/sim_light_driver.h"
#include "stage/sim/world_client.h"

namespace stage::sim {

// The table a light node steps through, as the schedule compiled it.
light::PatternTable TableFromSchedule(const v1::LightNodeTiming& timing);

// What a node program needs to put its sim device in stage-sim's world: the scene of its rig and a connection.
struct NodeWorld {
  std::shared_ptr<const SimScene> scene;
  std::unique_ptr<WorldClient> client;
};
absl::StatusOr<NodeWorld> OpenNodeWorld(const LoadedRig& loaded, const std::string& address);

// Attaches light node `node_id`'s driver to `world`; with `arm`, first loads its table from the scene's schedule and
// arms it (a world without takes; in takes the controller arms the node through its service). The node is late by its
// sim.extra_delay_us plus its sim.faults delay. `on_crash` runs at a crash fault; `on_edge` at every edge, with its
// time since slot 0.
absl::Status JoinLightNode(SimLightDriver* driver, const SimScene& scene, const std::string& node_id,
                           WorldClient* world, std::function<void()> on_crash = nullptr, bool arm = true,
                           std::function<void(int64_t)> on_edge = nullptr);

// The world attachment of camera `camera_id`: its trigger plan from the schedule, a renderer of the scene, and its
// faults from sim.faults.
absl::StatusOr<SimCameraWorld> CameraWorld(std::shared_ptr<const SimScene> scene, const std::string& camera_id,
                                           WorldClient* world);

// The rig's LED unit faults (dead, late) applied to `world`.
void ApplyUnitFaults(const SimScene& scene, World* world);

}  // namespace stage::sim
