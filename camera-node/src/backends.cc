// Camera backend selection.
#include "backends.h"

#include "absl/strings/str_cat.h"
#include "stage/sim/sim_camera_device.h"

namespace stage::camera {

absl::StatusOr<std::unique_ptr<CameraDevice>> CreateCameraDevice(const std::string& backend,
                                                                 const v1::CameraConfig& config, Clock* clock) {
  if (backend == "sim") {
    return std::make_unique<sim::SimCameraDevice>(clock, config.device().empty() ? config.id() : config.device());
  }
  if (backend == "aravis") {
    return absl::UnimplementedError(absl::StrCat("camera \"", config.id(),
                                                 "\": the aravis backend is not implemented yet; "
                                                 "run this camera with --backend sim"));
  }
  return absl::InvalidArgumentError(
      absl::StrCat("camera \"", config.id(), "\": unknown backend \"", backend, "\" (this build has: sim)"));
}

}  // namespace stage::camera
