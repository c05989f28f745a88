// ChArUco corners in an image (OpenCV's aruco module, kept inside charuco.cc).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
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
};

// The board's corners found in an 8-bit grey image (width x height, row-major): markers detected, corners
// interpolated and refined to subpixel. Empty when the board is not seen (or fewer than `min_corners` corners).
std::vector<CornerObservation> DetectCharuco(const std::vector<uint8_t>& grey, int width, int height,
                                             const CharucoBoardSpec& board, int min_corners = 6);

}  // namespace stage::processing
