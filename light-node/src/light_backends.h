// Light backends, registered in main() and chosen by the rig's `backend` (or --backend): the hardware ones here (gpiod,
// and modbus where this build has libmodbus), the simulator's in sim/ (sim/node_backends.h), registered only by a
// program built with the simulator. Nothing here links the simulator.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/common/backend_registry.h"
#include "stage/common/rig.h"
#include "stage/light/light_driver.h"
#include "stage/light/slot_clock.h"
#include "stage/v1/rig.pb.h"

namespace stage::light {

// Parses "sim", "gpiod", "modbus". InvalidArgument lists the valid names.
absl::StatusOr<v1::LightBackend> ParseLightBackend(const std::string& name);
std::string LightBackendName(v1::LightBackend backend);

// What a backend may need beyond the node's entry in the rig.
struct LightBackendContext {
  // The rig the node runs; not owned.
  const LoadedRig* rig = nullptr;
  // The rig's slot rate (a gpiod node generating the slot clock runs it at this rate).
  double slot_rate_hz = 912;
  // host:port of stage-sim's simulated world (--sim-world); empty on a real stage.
  std::string world_address;
  // With the world: load the table from the rig's schedule and arm at once (a world without takes).
  bool self_arm = false;
};

// What a backend makes for a node.
struct LightBackendParts {
  std::unique_ptr<LightDriver> driver;
  // The slot clock the node drives when the backend brings one apart from its driver (the simulated world's bus);
  // a driver's own (gpiod's clock output) comes with the driver.
  std::unique_ptr<SlotClockGenerator> slot_clock;
  // What must outlive the driver (a connection to the simulated world): destroyed after it.
  std::shared_ptr<void> keep;
};

class LightBackends
    : public BackendRegistry<v1::LightBackend, v1::LightNodeConfig, LightBackendContext, LightBackendParts> {
 public:
  LightBackends() : BackendRegistry("light node", &LightBackendName) {}
};
using LightBackendFactory = LightBackends::Factory;

// gpiod, and modbus where this build has libmodbus.
void RegisterHardwareLightBackends(LightBackends* backends);

}  // namespace stage::light
