// Camera backends by name, chosen from the rig (or --backend). Registered explicitly, never by static initializers.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/camera/camera_device.h"
#include "stage/common/clock.h"
#include "stage/v1/rig.pb.h"

namespace stage::camera {

// A device for `config` from backend `backend`. `clock` is used by the sim backend and must outlive the device.
// Unknown or unavailable backends give InvalidArgument naming the camera and the backends this build has.
absl::StatusOr<std::unique_ptr<CameraDevice>> CreateCameraDevice(const std::string& backend,
                                                                 const v1::CameraConfig& config, Clock* clock);

}  // namespace stage::camera
