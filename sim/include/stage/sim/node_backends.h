// The simulator's backends of the node programs, registered in their main() when they are built with the simulator
// (STAGE_WITH_SIM): a sim light driver and a sim camera, in stage-sim's world when the node is given its address.
#pragma once

#include <functional>

#include "camera_backends.h"
#include "light_backends.h"

namespace stage::sim {

// `on_crash` runs at a crash fault (sim.faults): the process dies as a crashed node would.
void RegisterSimLightBackend(light::LightBackends* backends, std::function<void()> on_crash);
void RegisterSimCameraBackend(camera::CameraBackends* backends, std::function<void()> on_crash);

}  // namespace stage::sim
