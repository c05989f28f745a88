// A calibrated camera of the stage: pinhole with Brown-Conrady distortion (OpenCV's model and order), placed as the
// rig says, at a scale of its sensor (the simulator's render scale; processing at the images' size). Camera frame as
// OpenCV's: x right, y down, z along the optical axis. Stage frame: +x the performer's left, +y up, +z towards the
// front cameras, millimetres.
#pragma once

#include <Eigen/Core>
#include <array>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/v1/rig.pb.h"

namespace stage {

// Every number of a camera model, as a calibration file holds it (camera_calibration.h).
struct CameraParameters {
  int width = 0, height = 0;                 // pixels
  double fx = 0, fy = 0, cx = 0, cy = 0;     // pixels; pixel centres at integers
  std::array<double, 5> distortion{};        // k1, k2, p1, p2, k3
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // centre of projection, stage frame, mm
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // world -> camera
};

class CameraModel {
 public:
  CameraModel() = default;
  // From the rig's camera entry; `render_scale` in (0, 1] scales the sensor (width, height, focal length in pixels,
  // principal point). InvalidArgument names the camera and the field.
  static absl::StatusOr<CameraModel> FromConfig(const v1::CameraConfig& config, double render_scale);

  // From explicit numbers; InvalidArgument when the size or a focal length is not positive, or the rotation is not
  // one (orthonormal to 1e-6, determinant +1).
  static absl::StatusOr<CameraModel> FromParameters(const CameraParameters& p);
  CameraParameters parameters() const;
  // This model (of the whole sensor) at `render_scale` in (0, 1]: the size rounded in each axis, intrinsics scaled
  // about pixel corners, as FromConfig scales.
  CameraModel Scaled(double render_scale) const;
  // This model at another image size of the same sensor (scaled about pixel corners in each axis).
  CameraModel Resized(int width, int height) const;

  int width() const { return width_; }
  int height() const { return height_; }
  // Intrinsics at the render scale, pixels.
  double fx() const { return fx_; }
  double fy() const { return fy_; }
  double cx() const { return cx_; }
  double cy() const { return cy_; }
  const std::array<double, 5>& distortion() const { return distortion_; }
  // Centre of projection, stage frame, mm.
  const Eigen::Vector3d& position() const { return position_; }
  // Rows: the camera's x, y, z axes in the stage frame (world -> camera rotation).
  const Eigen::Matrix3d& rotation() const { return rotation_; }
  Eigen::Vector3d optical_axis() const { return rotation_.row(2).transpose(); }

  // The pixel (x right, y down; pixel centres at integers) where stage point `p` appears; false if it is behind the
  // camera.
  bool Project(const Eigen::Vector3d& p, Eigen::Vector2d* pixel) const;

  // Unit ray direction in the stage frame through the centre of every pixel, row-major (undistorted with OpenCV's
  // iterative inverse of the distortion model); through (x + dx, y + dy) of each pixel with an offset in pixels.
  std::vector<Eigen::Vector3f> PixelRays(double dx = 0, double dy = 0) const;

 private:
  int width_ = 0, height_ = 0;
  double fx_ = 0, fy_ = 0, cx_ = 0, cy_ = 0;
  std::array<double, 5> distortion_{};
  Eigen::Vector3d position_ = Eigen::Vector3d::Zero();
  Eigen::Matrix3d rotation_ = Eigen::Matrix3d::Identity();
};

}  // namespace stage
