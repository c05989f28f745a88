// ChArUco corners in an image (OpenCV's aruco module, kept inside charuco.cc).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/photometric.h"
#include "stage/v1/rig.pb.h"

namespace stage::processing {

// The board: squares, their size, the markers' dictionary (the rig's sim.subject.board describes the printed board).
struct CharucoBoardSpec {
  int squares_x = 11, squares_y = 9;
  double square_mm = 30, marker_mm = 22;
  std::string dictionary = "DICT_5X5_100";

  static CharucoBoardSpec FromRig(const v1::SimBoard& board);
  // InvalidArgument naming the field: sizes, a marker not inside its square, an unknown dictionary, too few markers.
  absl::Status Validate() const;
  // The chessboard corners by OpenCV's corner id, in the board's own frame (z = 0), mm.
  std::vector<Eigen::Vector3d> Corners() const;
};

struct CornerObservation {
  int id = 0;
  // Pixel, x right, y down, pixel centres at integers (the camera model's convention).
  Eigen::Vector2d pixel = Eigen::Vector2d::Zero();
  // The corner's expected error, pixels (0: not known): RefineCorners sets it from the window the corner was refined
  // in; bundle adjustment weighs the corner by it.
  double sigma_px = 0;
};

// The board's corners found in a linear grey image (1 channel): markers detected on an 8-bit copy (its 99th
// percentile at 230), corners interpolated by OpenCV, then refined on the linear image (RefineCorners). Empty when the
// board is not seen (or fewer than `min_corners` corners).
std::vector<CornerObservation> DetectCharuco(const Image& grey, const CharucoBoardSpec& board, int min_corners = 6);

// Each corner (pixel centres at integers) moved to the chessboard's saddle point: the image around it smoothed by a
// Gaussian and cv::cornerSubPix run to 0.001 px, with window and smoothing sized to the plain chessboard about the
// corner as the view shows it (the margin between a square's edge and its marker, through the Jacobian of the
// homography from the board to the view's corners: foreshortened and sheared), so that only the plain chessboard and
// the markers' black borders enter, never a marker's inner cells. OpenCV 4.6's own ChArUco refinement stops once a
// step is under 0.1 px and works on the raw pixels, whose box-filtered edges pull a corner towards the pixel grid
// ("pixel locking"): 0.12 px in the median on the simulator's board at render scale 0.25, 0.023 px this way
// (charuco_sim_test.cc). Dropped: a corner whose edges meet at under 58 degrees (a square seen sheared), one with no
// room for a 5 x 5 window, one whose refinement wanders further than its margin allows. Each corner's sigma_px is set
// from its window.
std::vector<CornerObservation> RefineCorners(const Image& grey, const CharucoBoardSpec& board,
                                             std::vector<CornerObservation> corners);

}  // namespace stage::processing
