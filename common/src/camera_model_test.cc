// Camera geometry from the rig: pose and orientation as the rig says, distortion round trip, render scale.
#include "stage/common/camera_model.h"

#include "gtest/gtest.h"

namespace stage {
namespace {

v1::CameraConfig Config() {
  v1::CameraConfig c;
  c.set_id("mv-x");
  c.set_width(2592);
  c.set_height(2048);
  c.mutable_intrinsics()->set_focal_length_mm(35);
  c.mutable_intrinsics()->set_pixel_size_um(4.8);
  c.mutable_pose()->mutable_position_mm()->set_z(1000);
  c.mutable_pose()->mutable_up()->set_y(1);
  return c;
}

TEST(CameraModelTest, LooksAtItsTargetWithUpUpAndThePerformersLeftOnTheRight) {
  auto cam = CameraModel::FromConfig(Config(), 1.0);
  ASSERT_TRUE(cam.ok()) << cam.status();
  Eigen::Vector2d px;
  ASSERT_TRUE(cam->Project({0, 0, 0}, &px));
  EXPECT_NEAR(px.x(), (2592 - 1) / 2.0, 1e-9);
  EXPECT_NEAR(px.y(), (2048 - 1) / 2.0, 1e-9);
  // A point above the head appears higher in the image (smaller y); the performer's left (+x) on the image's right.
  Eigen::Vector2d above, left;
  ASSERT_TRUE(cam->Project({0, 50, 0}, &above));
  ASSERT_TRUE(cam->Project({50, 0, 0}, &left));
  EXPECT_LT(above.y(), px.y());
  EXPECT_GT(left.x(), px.x());
  // 50 mm at 1000 mm with f = 35 mm / 4.8 um = 7291.67 px: 364.58 px.
  EXPECT_NEAR(left.x() - px.x(), 7291.6667 * 0.05, 1e-3);
  EXPECT_FALSE(cam->Project({0, 0, 2000}, &px));  // behind the camera
}

TEST(CameraModelTest, PixelRaysInvertTheDistortedProjection) {
  v1::CameraConfig c = Config();
  for (double k : {-0.12, 0.05, 0.0008, -0.0006, 0.01}) c.mutable_intrinsics()->add_distortion(k);
  c.mutable_intrinsics()->set_principal_offset_x_px(12);
  auto cam = CameraModel::FromConfig(c, 0.05);  // 130 x 102
  ASSERT_TRUE(cam.ok());
  EXPECT_EQ(cam->width(), 130);
  EXPECT_EQ(cam->height(), 102);
  const std::vector<Eigen::Vector3f> rays = cam->PixelRays();
  ASSERT_EQ(rays.size(), 130u * 102u);
  double worst = 0;
  for (int v = 0; v < cam->height(); v += 7) {
    for (int u = 0; u < cam->width(); u += 7) {
      const Eigen::Vector3d p = cam->position() + 1000.0 * rays[static_cast<size_t>(v) * 130 + u].cast<double>();
      Eigen::Vector2d px;
      ASSERT_TRUE(cam->Project(p, &px));
      worst = std::max(worst, (px - Eigen::Vector2d(u, v)).norm());
    }
  }
  EXPECT_LT(worst, 1e-3) << "pixels";
}

TEST(CameraModelTest, BadConfigurationIsNamed) {
  v1::CameraConfig c = Config();
  c.mutable_pose()->mutable_up()->set_y(0);
  c.mutable_pose()->mutable_up()->set_z(1);  // parallel to the optical axis
  auto cam = CameraModel::FromConfig(c, 1.0);
  ASSERT_FALSE(cam.ok());
  EXPECT_NE(cam.status().message().find("mv-x"), std::string::npos);
  EXPECT_FALSE(CameraModel::FromConfig(Config(), 0).ok());
}

}  // namespace
}  // namespace stage
