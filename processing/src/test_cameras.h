// Cameras for processing's unit tests: a pinhole without distortion placed anywhere, looking at a point.
#pragma once

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "stage/common/camera_model.h"

namespace stage::processing {

// A `width` x `height` camera of focal length `f` pixels (principal point at the centre) at `position`, looking at
// `target`, image y down along the stage's -y as far as the view allows (not straight up or down).
inline CameraModel CameraLookingAt(const Eigen::Vector3d& position, const Eigen::Vector3d& target, int width,
                                   int height, double f) {
  CameraParameters p;
  p.width = width;
  p.height = height;
  p.fx = p.fy = f;
  p.cx = (width - 1) / 2.0;
  p.cy = (height - 1) / 2.0;
  p.position = position;
  const Eigen::Vector3d z = (target - position).normalized();
  const Eigen::Vector3d x = Eigen::Vector3d::UnitY().cross(z).normalized() * -1;  // image x to the right
  const Eigen::Vector3d y = z.cross(x);                                           // image y down
  p.rotation.row(0) = x;
  p.rotation.row(1) = y;
  p.rotation.row(2) = z;
  auto model = CameraModel::FromParameters(p);
  EXPECT_TRUE(model.ok()) << model.status();
  return *model;
}

}  // namespace stage::processing
