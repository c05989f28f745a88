// Camera backend selection.
#include "backends.h"

#ifndef STAGE_WITH_ARAVIS
#define STAGE_WITH_ARAVIS 0
#endif

#include "absl/strings/str_cat.h"
#include "stage/sim/sim_camera_device.h"
#if STAGE_WITH_ARAVIS
#include "aravis_camera_device.h"
#endif

namespace stage::camera {
namespace {
std::string Backends() { return STAGE_WITH_ARAVIS ? "sim, aravis" : "sim"; }
}  // namespace

absl::StatusOr<std::unique_ptr<CameraDevice>> CreateCameraDevice(const std::string& backend,
                                                                 const v1::CameraConfig& config, Clock* clock) {
  if (backend == "sim") {
    return std::make_unique<sim::SimCameraDevice>(clock, config.device().empty() ? config.id() : config.device());
  }
  if (backend == "aravis") {
#if STAGE_WITH_ARAVIS
    if (config.device().empty()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "camera \"", config.id(), "\": the aravis backend needs the camera's device (serial, user id or address)"));
    }
    auto device = AravisCameraDevice::Open(config.id(), config.device());
    if (!device.ok()) return device.status();
    return std::unique_ptr<CameraDevice>(std::move(*device));
#else
    return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(),
                                                   "\": this build has no aravis backend (built with "
                                                   "STAGE_WITH_ARAVIS=OFF); it has: ", Backends()));
#endif
  }
  return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(), "\": unknown backend \"", backend,
                                                 "\" (this build has: ", Backends(), ")"));
}

}  // namespace stage::camera
