// Bundle adjustment of a calibration take (Ceres, kept inside bundle_adjustment.cc): every camera's intrinsics
// (focal lengths, principal point, distortion k1 k2 p1 p2, optionally k3) and pose, and the board's pose in every
// frame, fitted to the ChArUco corners every camera saw, under a robust loss.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <map>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "charuco.h"
#include "stage/common/camera_model.h"

namespace stage::processing {

// What one camera saw of the board: its corners per frame.
struct CameraObservations {
  std::string id;
  // The model at the images' size: the starting point, and what the fit returns.
  CameraModel model;
  std::map<int64_t, std::vector<CornerObservation>> frames;
};

// The board's pose: board frame -> stage frame.
using BoardPoses = std::map<int64_t, Eigen::Isometry3d>;

struct BundleOptions {
  // Residuals beyond this (pixels) weigh less (Huber loss). Default 0.5.
  double loss_px = 0.5;
  // Fit the sixth-order radial term k3 too (it trades off against k1, k2 with a small board). Default false.
  bool fit_k3 = false;
  // Corners whose residual after a first fit is beyond this many times the camera's RMS (and 0.5 px) are dropped
  // before the final fit. Default 4.
  double outlier_factor = 4;
  int max_iterations = 200;
  // The board pose of this frame is held fixed (the fit's gauge); -1: the first frame.
  int64_t fixed_frame = -1;
};

struct BundleCameraResult {
  double rms_px = 0;
  int corners_used = 0, corners_dropped = 0, frames = 0;
};

struct BundleResult {
  std::vector<CameraModel> cameras;  // in the order given, at the images' size
  std::vector<BundleCameraResult> per_camera;
  BoardPoses boards;
  double rms_px = 0;
  int iterations = 0;
  std::string report;  // Ceres's brief report
};

// Every camera in `cameras` must have observations and every frame they name a pose in `boards`. FailedPrecondition
// when the fit does not converge to a usable solution.
absl::StatusOr<BundleResult> BundleAdjust(const std::vector<Eigen::Vector3d>& board_corners,
                                          const std::vector<CameraObservations>& cameras, const BoardPoses& boards,
                                          const BundleOptions& options);

}  // namespace stage::processing
