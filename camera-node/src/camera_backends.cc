// Camera backends: see backends.h.
#include "camera_backends.h"

#ifndef STAGE_WITH_ARAVIS
#define STAGE_WITH_ARAVIS 0
#endif

#include "absl/strings/str_cat.h"
#if STAGE_WITH_ARAVIS
#include "aravis_camera_device.h"
#endif

namespace stage::camera {

absl::StatusOr<v1::CameraBackend> ParseCameraBackend(const std::string& name) {
  if (name == "sim") return v1::CAMERA_BACKEND_SIM;
  if (name == "aravis") return v1::CAMERA_BACKEND_ARAVIS;
  return absl::InvalidArgumentError(absl::StrCat("unknown camera backend \"", name, "\" (sim, aravis)"));
}

std::string CameraBackendName(v1::CameraBackend backend) {
  switch (backend) {
    case v1::CAMERA_BACKEND_SIM:
      return "sim";
    case v1::CAMERA_BACKEND_ARAVIS:
      return "aravis";
    default:
      return "unspecified";
  }
}

void RegisterHardwareCameraBackends(CameraBackends* backends) {
#if STAGE_WITH_ARAVIS
  backends->Register(
      v1::CAMERA_BACKEND_ARAVIS, [](const v1::CameraConfig& config, const CameraBackendContext&) -> absl::StatusOr<CameraBackendParts> {
        if (config.device().empty()) {
          return absl::InvalidArgumentError(
              absl::StrCat("camera \"", config.id(),
                           "\": the aravis backend needs the camera's device (serial, user id or address)"));
        }
        auto device = AravisCameraDevice::Open(config.id(), config.device());
        if (!device.ok()) return device.status();
        CameraBackendParts parts;
        parts.device = std::move(*device);
        parts.start_now = config.trigger().source() == v1::TRIGGER_SOURCE_HARDWARE_LINE;
        return parts;
      });
#else
  (void)backends;
#endif
}

}  // namespace stage::camera
