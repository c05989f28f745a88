// Camera geometry from the rig.
#include "stage/common/camera_model.h"

#include <Eigen/Geometry>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "absl/strings/str_cat.h"

namespace stage {
namespace {

Eigen::Vector3d ToEigen(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

}  // namespace

absl::StatusOr<CameraModel> CameraModel::FromConfig(const v1::CameraConfig& config, double render_scale) {
  auto bad = [&](absl::string_view what) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(), "\": ", what));
  };
  if (!(render_scale > 0 && render_scale <= 1))
    return bad(absl::StrCat("render scale ", render_scale, " is not in (0, 1]"));
  if (config.width() == 0 || config.height() == 0) return bad("width and height are required");
  const auto& in = config.intrinsics();
  if (!(in.focal_length_mm() > 0) || !(in.pixel_size_um() > 0)) {
    return bad("intrinsics.focal_length_mm and pixel_size_um must be > 0");
  }
  if (in.distortion_size() > 5) return bad("intrinsics.distortion has more than 5 coefficients");
  CameraModel m;
  m.width_ = static_cast<int>(config.width());
  m.height_ = static_cast<int>(config.height());
  const double f_px = in.focal_length_mm() / (in.pixel_size_um() * 1e-3);
  m.fx_ = f_px;
  m.fy_ = f_px;
  m.cx_ = (config.width() - 1) / 2.0 + in.principal_offset_x_px();
  m.cy_ = (config.height() - 1) / 2.0 + in.principal_offset_y_px();
  for (int i = 0; i < in.distortion_size(); ++i) m.distortion_[i] = in.distortion(i);

  const Eigen::Vector3d position = ToEigen(config.pose().position_mm());
  const Eigen::Vector3d look_at = ToEigen(config.pose().look_at_mm());
  Eigen::Vector3d up = config.pose().has_up() ? ToEigen(config.pose().up()) : Eigen::Vector3d(0, 1, 0);
  const Eigen::Vector3d forward = (look_at - position).normalized();
  if ((look_at - position).norm() < 1e-9) return bad("pose.look_at_mm is the camera position");
  Eigen::Vector3d right = forward.cross(up);
  if (right.norm() < 1e-9) return bad("pose.up is parallel to the optical axis");
  right.normalize();
  const Eigen::Vector3d down = forward.cross(right);  // OpenCV's y axis: image down
  m.rotation_.row(0) = right.transpose();
  m.rotation_.row(1) = down.transpose();
  m.rotation_.row(2) = forward.transpose();
  m.position_ = position;
  return m.Scaled(render_scale);
}

absl::StatusOr<CameraModel> CameraModel::FromParameters(const CameraParameters& p) {
  if (p.width <= 0 || p.height <= 0) return absl::InvalidArgumentError("the image size must be positive");
  if (!(p.fx > 0) || !(p.fy > 0)) return absl::InvalidArgumentError("the focal lengths must be positive");
  const double orthonormal = (p.rotation * p.rotation.transpose() - Eigen::Matrix3d::Identity()).norm();
  if (!(orthonormal < 1e-6) || !(p.rotation.determinant() > 0)) {
    return absl::InvalidArgumentError("the rotation is not a rotation matrix");
  }
  for (double v : {p.cx, p.cy, p.position.x(), p.position.y(), p.position.z()}) {
    if (!std::isfinite(v)) return absl::InvalidArgumentError("the principal point and position must be finite");
  }
  CameraModel m;
  m.width_ = p.width;
  m.height_ = p.height;
  m.fx_ = p.fx;
  m.fy_ = p.fy;
  m.cx_ = p.cx;
  m.cy_ = p.cy;
  m.distortion_ = p.distortion;
  m.position_ = p.position;
  m.rotation_ = p.rotation;
  return m;
}

CameraParameters CameraModel::parameters() const {
  return {width_, height_, fx_, fy_, cx_, cy_, distortion_, position_, rotation_};
}

CameraModel CameraModel::Scaled(double render_scale) const {
  return Resized(std::max(1, static_cast<int>(std::lround(width_ * render_scale))),
                 std::max(1, static_cast<int>(std::lround(height_ * render_scale))));
}

CameraModel CameraModel::Resized(int width, int height) const {
  CameraModel m = *this;
  m.width_ = width;
  m.height_ = height;
  // Scale about pixel corners: a pixel of the smaller image covers width_ / width pixels of this one.
  const double sx = static_cast<double>(width) / width_;
  const double sy = static_cast<double>(height) / height_;
  m.fx_ = fx_ * sx;
  m.fy_ = fy_ * sy;
  m.cx_ = (cx_ + 0.5) * sx - 0.5;
  m.cy_ = (cy_ + 0.5) * sy - 0.5;
  return m;
}

bool CameraModel::Project(const Eigen::Vector3d& p, Eigen::Vector2d* pixel) const {
  const Eigen::Vector3d c = rotation_ * (p - position_);
  if (c.z() <= 0) return false;
  const double x = c.x() / c.z(), y = c.y() / c.z();
  const auto& d = distortion_;  // k1, k2, p1, p2, k3
  const double r2 = x * x + y * y;
  const double radial = 1 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2 * r2 * r2;
  const double xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x);
  const double yd = y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y;
  *pixel = {fx_ * xd + cx_, fy_ * yd + cy_};
  return true;
}

std::vector<Eigen::Vector3f> CameraModel::PixelRays(double dx, double dy) const {
  std::vector<cv::Point2d> pixels;
  pixels.reserve(static_cast<size_t>(width_) * height_);
  for (int v = 0; v < height_; ++v) {
    for (int u = 0; u < width_; ++u) pixels.emplace_back(u + dx, v + dy);
  }
  const cv::Matx33d k(fx_, 0, cx_, 0, fy_, cy_, 0, 0, 1);
  const cv::Mat dist(1, 5, CV_64F, const_cast<double*>(distortion_.data()));
  std::vector<cv::Point2d> normalized;
  // Iterations beyond OpenCV's default 5: the stage's lenses are mild, but the tests check the round trip tightly.
  cv::undistortPoints(pixels, normalized, k, dist, cv::noArray(), cv::noArray(),
                      cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 50, 1e-12));
  std::vector<Eigen::Vector3f> rays(normalized.size());
  const Eigen::Matrix3d to_world = rotation_.transpose();
  for (size_t i = 0; i < normalized.size(); ++i) {
    rays[i] = (to_world * Eigen::Vector3d(normalized[i].x, normalized[i].y, 1.0)).normalized().cast<float>();
  }
  return rays;
}

}  // namespace stage
