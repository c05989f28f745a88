// A calibration file: every camera's measured intrinsics and pose at its whole sensor, what processing uses in place
// of the rig's nominal models (docs/geometry.md#calibration-files). `stage-process calibrate` writes one from a
// calibration take; the simulator writes its cameras' truth in the same form (ground_truth/cameras.json).
//
//   {"format": "fastage-camera-calibration", "version": 1, "source": "...",
//    "cameras": [{"id": "mv-01", "width": 2592, "height": 2048, "fx": ..., "fy": ..., "cx": ..., "cy": ...,
//                 "distortion": [k1, k2, p1, p2, k3], "position_mm": [x, y, z],
//                 "rotation": [9 numbers, row-major, world -> camera (OpenCV's camera frame)]}, ...]}
#pragma once

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/common/camera_model.h"

namespace stage {

struct CalibratedCamera {
  std::string id;
  CameraModel model;  // the whole sensor
};

struct CameraCalibration {
  // Where it came from, for the record ("simulator truth", "calibration take <dir>").
  std::string source;
  std::vector<CalibratedCamera> cameras;

  // The camera's model, or null.
  const CameraModel* Find(const std::string& id) const;
};

// Errors name the file and the field ("cameras[3].rotation: not a rotation").
absl::StatusOr<CameraCalibration> ReadCameraCalibration(const std::string& path);
// Written atomically (a temporary file renamed over `path`).
absl::Status WriteCameraCalibration(const std::string& path, const CameraCalibration& calibration);

}  // namespace stage
