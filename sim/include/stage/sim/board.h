// The ChArUco calibration board as a subject: OpenCV's board (chessboard squares, ArUco markers in the white ones)
// printed on a flat plate, posed by a performance like the head (rotation about its centre, then translation). Its
// ChArUco corners in any pose are the ground truth a calibration is checked against.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/sim/head.h"
#include "stage/v1/rig.pb.h"

namespace stage::sim {

class BoardModel final : public RiggedModel {
 public:
  // The board of the rig's sim.subject.board (defaults applied); errors name the field.
  static absl::StatusOr<std::shared_ptr<const BoardModel>> Create(const v1::SimBoard& board);

  // Part 0 is the printed face (paper white, ink black, matte), part 1 the plate's grey back.
  SurfaceSample Surface(const Eigen::Vector2f& uv, int part,
                        const std::array<float, kExpressionCount>& expression) const override;
  // A plate shadows none of itself: a point of its print sees every light in front of it, so the renderer skips the
  // shadow rays (a third of a calibration take's rendering). The plate is its two faces, open at the rim: the few
  // pixels at its edge whose rays pass the rim and meet a face from inside are lit as its outside would be.
  bool Convex() const override { return true; }

  // The ChArUco corners, indexed by OpenCV's corner id, in the board's neutral place (z = 0, facing +z), mm.
  const std::vector<Eigen::Vector3f>& corners() const { return corners_; }
  // The corners where `pose` puts them.
  std::vector<Eigen::Vector3f> CornersAt(const HeadPose& pose) const;
  // Size of the printed area, mm.
  float width_mm() const { return width_mm_; }
  float height_mm() const { return height_mm_; }
  // The printed face as an 8-bit grey image, row 0 at v = 0.
  const std::vector<uint8_t>& texture() const { return texture_; }
  int texture_width() const { return texture_width_; }
  int texture_height() const { return texture_height_; }

  // Reflectance of the paper and the ink.
  static constexpr float kWhite = 0.85f, kBlack = 0.04f;

 private:
  BoardModel() = default;
  std::vector<Eigen::Vector3f> corners_;
  float width_mm_ = 0, height_mm_ = 0;
  std::vector<uint8_t> texture_;
  int texture_width_ = 0, texture_height_ = 0;
};

// Performance::Default's counterpart for the board: 5 s of turns towards every camera (up to 105 degrees each way),
// tilts, rolls and shifts through the head's volume (up to 120 mm, depth too) that a
// camera calibration wants, starting and ending square to the +z axis.
Performance BoardSequence();

}  // namespace stage::sim
