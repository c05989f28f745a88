// The solving part of calibration (calibrate.cc), apart from reading takes: for tests on synthetic observations.
#pragma once

#include <vector>

#include "absl/status/statusor.h"
#include "bundle_adjustment.h"

namespace stage::processing {

// Every frame's board pose and every camera's pose started from the cameras' models (the rig's nominal ones: each
// frame's board placed by the view the other views agree with best, then each camera placed by all the corners it
// saw), then one bundle adjustment; the result moved by the rigid motion that best puts the fitted centres on the
// starting ones (the stage frame as the rig defines it).
absl::StatusOr<BundleResult> SolveCalibration(const std::vector<Eigen::Vector3d>& board_corners,
                                              std::vector<CameraObservations> cameras, const BundleOptions& options);

}  // namespace stage::processing
