// A camera as photometric processing sees it: its geometry (the rig's intrinsics and pose, scaled to the recorded
// images) and its radiometric calibration (docs/processing.md#calibration): the rig's `photometric` entry, or, for a
// simulated camera, what the simulator's sensor model gives for every field the entry leaves out.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/camera_model.h"
#include "stage/common/rig.h"
#include "stage/processing/light_model.h"
#include "stage/processing/photometric.h"

namespace stage::processing {

struct CameraSetup {
  CameraModel model;          // at the recorded size
  PhotometricCamera camera;   // rays, noise model, white level, leak
  double black_level_dn = 0;  // removed from every frame
  std::string flat_field;     // image file (absolute path); empty: none
  // Where the calibration came from, for the record: "rig", or "simulator" for the fields it derived.
  std::string source;
};

// The whole-sensor model of camera `camera_id` (from `calibration`, or the rig's nominal one when it is null) at the
// size its frames were recorded at: the take's render scale (simulated cameras) or the whole sensor. Errors name the
// camera: not in the rig or the calibration, frames of a size neither gives.
absl::StatusOr<CameraModel> CameraAtImageSize(const LoadedRig& rig, const std::string& camera_id, int width, int height,
                                              const CameraCalibration* calibration = nullptr);

// Camera `camera_id` of `rig`, recorded at width x height with `bits` of data (8, 12 or 16), placed as `calibration`
// says (a calibration file: camera_calibration.h), or where the rig's nominal model says when it is null. Errors
// name the camera and the field: no such camera, not in the calibration, no radiometric calibration for a real
// camera, a value out of range.
absl::StatusOr<CameraSetup> ResolveCamera(const LoadedRig& rig, const LightModel& light, const std::string& camera_id,
                                          int width, int height, int bits,
                                          const CameraCalibration* calibration = nullptr);

}  // namespace stage::processing
