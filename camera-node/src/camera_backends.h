// Camera backends, registered in main() and chosen by the rig's `backend` (or --backend): the hardware one here
// (aravis, where this build has Aravis), the simulator's in sim/ (sim/node_backends.h), registered only by a program
// built with the simulator. Nothing here links the simulator.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/camera/camera_device.h"
#include "stage/common/backend_registry.h"
#include "stage/common/clock.h"
#include "stage/common/rig.h"
#include "stage/v1/rig.pb.h"

namespace stage::camera {

// What a backend may need beyond the camera's entry in the rig.
struct CameraBackendContext {
  // The rig the node runs; not owned.
  const LoadedRig* rig = nullptr;
  // The node's clock (frame timestamps where the device has none of its own); outlives the device.
  Clock* clock = nullptr;
  // host:port of stage-sim's simulated world (--sim-world); empty on a real stage.
  std::string world_address;
};

// What a backend makes for a node.
struct CameraBackendParts {
  std::unique_ptr<CameraDevice> device;
  // The device acquires from the start, waiting for its trigger line's edges (a camera on the hardware line; in the
  // simulated world, the world's bus): frames outside a take are counted and not recorded.
  bool start_now = false;
  // What must outlive the device (a connection to the simulated world): destroyed after it.
  std::shared_ptr<void> keep;
};

// The rig's short names ("sim", "aravis"), for --backend and messages.
absl::StatusOr<v1::CameraBackend> ParseCameraBackend(const std::string& name);
std::string CameraBackendName(v1::CameraBackend backend);

class CameraBackends
    : public BackendRegistry<v1::CameraBackend, v1::CameraConfig, CameraBackendContext, CameraBackendParts> {
 public:
  CameraBackends() : BackendRegistry("camera", &CameraBackendName) {}
};
using CameraBackendFactory = CameraBackends::Factory;

// aravis, where this build has Aravis.
void RegisterHardwareCameraBackends(CameraBackends* backends);

}  // namespace stage::camera
