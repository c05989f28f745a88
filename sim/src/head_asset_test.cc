// A user's own head from files: OBJ blendshapes move the mesh as the weights say, the images give the material (sRGB
// albedo decoded, specular scaled, tangent-space normals tilting the shading normal by their angle), the rig wires it
// into the scene, and bad files are refused with the file or expression named.
#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/sim/head.h"
#include "stage/sim/scene.h"

namespace stage::sim {
namespace {

using ::testing::HasSubstr;

constexpr float kTiltDeg = 20;

float SrgbToLinear(float v) { return v <= 0.04045f ? v / 12.92f : std::pow((v + 0.055f) / 1.055f, 2.4f); }

// Writes a head asset made from the procedural head at low resolution; returns its files.
HeadAssetFiles WriteAsset(const std::string& dir) {
  std::filesystem::create_directories(dir);
  auto procedural = HeadModel::Procedural(3, 64);
  HeadPose jaw;
  jaw.expression[ExpressionIndex("jaw_open")] = 1;
  EXPECT_TRUE(WriteObj(dir + "/neutral.obj", procedural->neutral()).ok());
  EXPECT_TRUE(WriteObj(dir + "/jaw.obj", procedural->PosedMesh(jaw)).ok());
  // Albedo: sRGB (R, G, B) = (200, 120, 90) on the left half (u < 0.5), (60, 40, 30) on the right.
  cv::Mat albedo(32, 64, CV_8UC3);
  albedo(cv::Rect(0, 0, 32, 32)).setTo(cv::Scalar(90, 120, 200));
  albedo(cv::Rect(32, 0, 32, 32)).setTo(cv::Scalar(30, 40, 60));
  EXPECT_TRUE(cv::imwrite(dir + "/albedo.png", albedo));
  cv::Mat specular(32, 64, CV_16U, cv::Scalar(static_cast<int>(0.3 * 65535)));
  EXPECT_TRUE(cv::imwrite(dir + "/specular.png", specular));
  // A normal map tilted by kTiltDeg towards +u everywhere: (sin, 0, cos) in [0, 1] as 16-bit B, G, R.
  const double t = kTiltDeg * M_PI / 180;
  auto enc = [](double v) { return (v + 1) / 2 * 65535; };
  cv::Mat normal(32, 64, CV_16UC3, cv::Scalar(enc(std::cos(t)), enc(0), enc(std::sin(t))));
  EXPECT_TRUE(cv::imwrite(dir + "/normal.png", normal));
  HeadAssetFiles files;
  files.neutral_obj = dir + "/neutral.obj";
  files.blendshapes = {{"jaw_open", dir + "/jaw.obj"}};
  files.albedo = dir + "/albedo.png";
  files.specular = dir + "/specular.png";
  files.normal = dir + "/normal.png";
  return files;
}

TEST(HeadAssetTest, BlendshapesMoveTheMeshAsTheWeightsSay) {
  const std::string dir = ::testing::TempDir() + "/head-asset-blend";
  auto head = HeadModel::FromAsset(WriteAsset(dir));
  ASSERT_TRUE(head.ok()) << head.status();
  auto procedural = HeadModel::Procedural(3, 64);
  EXPECT_TRUE((*head)->HasBlendshape(ExpressionIndex("jaw_open")));
  EXPECT_FALSE((*head)->HasBlendshape(ExpressionIndex("smile_left")));
  HeadPose pose;
  pose.expression[ExpressionIndex("jaw_open")] = 0.6f;
  pose.expression[ExpressionIndex("smile_left")] = 1;  // no blendshape: no motion
  pose.rotation_deg = {15, -5, 3};
  pose.translation_mm = {4, -2, 7};
  HeadPose expected = pose;
  expected.expression[ExpressionIndex("smile_left")] = 0;
  const TriangleMesh mine = (*head)->PosedMesh(pose);
  const TriangleMesh theirs = procedural->PosedMesh(expected);
  // The OBJ reader numbers vertices as the faces first use them: compare triangle by triangle.
  ASSERT_EQ(mine.triangles.size(), theirs.triangles.size());
  float worst = 0;
  for (size_t t = 0; t < mine.triangles.size(); ++t) {
    for (int k = 0; k < 3; ++k) {
      worst = std::max(worst, (mine.positions[mine.triangles[t][k]] - theirs.positions[theirs.triangles[t][k]]).norm());
    }
  }
  EXPECT_LT(worst, 1e-3f);  // mm: the OBJ's 4 decimals
}

TEST(HeadAssetTest, ImagesGiveTheMaterialAndTheDetailNormals) {
  const std::string dir = ::testing::TempDir() + "/head-asset-maps";
  HeadAssetFiles files = WriteAsset(dir);
  files.specular_scale = 0.1f;
  files.roughness_value = 0.27f;
  auto head = HeadModel::FromAsset(files);
  ASSERT_TRUE(head.ok()) << head.status();
  const SurfaceSample left = (*head)->Surface({0.2f, 0.5f}, 0, {});
  EXPECT_NEAR(left.material.albedo.x(), SrgbToLinear(200 / 255.0f), 1e-4);
  EXPECT_NEAR(left.material.albedo.y(), SrgbToLinear(120 / 255.0f), 1e-4);
  EXPECT_NEAR(left.material.albedo.z(), SrgbToLinear(90 / 255.0f), 1e-4);
  const SurfaceSample right = (*head)->Surface({0.8f, 0.5f}, 0, {});
  EXPECT_NEAR(right.material.albedo.x(), SrgbToLinear(60 / 255.0f), 1e-4);
  EXPECT_NEAR(left.material.specular, 0.03f, 1e-4);
  EXPECT_FLOAT_EQ(left.material.roughness, 0.27f);

  // The shading normal leans kTiltDeg from the mesh's own, wherever the ray meets the face.
  MeshSubject plain((*head)->neutral(), nullptr);
  auto mapped = (*head)->Posed(HeadPose{});
  int checked = 0;
  for (float x = -30; x <= 30; x += 15) {
    for (float y = -40; y <= 40; y += 20) {
      const Eigen::Vector3f origin(x, y, 600), d(0, 0, -1);
      const Hit a = plain.Intersect(origin, d), b = mapped->Intersect(origin, d);
      ASSERT_TRUE(a.hit && b.hit);
      if (b.normal.dot(b.geometric_normal) <= 0.05f + 1e-3f) continue;  // clamped at a grazing angle
      const float angle = std::acos(std::clamp(a.normal.dot(b.normal), -1.0f, 1.0f)) * 180 / static_cast<float>(M_PI);
      EXPECT_NEAR(angle, kTiltDeg, 0.5) << x << "," << y;
      ++checked;
    }
  }
  EXPECT_GE(checked, 20);
}

TEST(HeadAssetTest, TheRigPutsTheUsersHeadOnStage) {
  const std::string dir = ::testing::TempDir() + "/head-asset-rig";
  WriteAsset(dir);
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  LoadedRig mine = *loaded;
  mine.base_dir = dir;
  auto* subject = mine.rig.mutable_sim()->mutable_subject();
  subject->mutable_asset()->set_neutral_obj("neutral.obj");
  (*subject->mutable_asset()->mutable_blendshapes())["jaw_open"] = "jaw.obj";
  subject->mutable_asset()->set_albedo("albedo.png");
  mine.rig.mutable_sim()->set_render_scale(0.05);
  ApplyRigDefaults(&mine.rig);
  EXPECT_TRUE(ValidateRig(mine.rig, dir).empty());
  EXPECT_FLOAT_EQ(subject->asset().pivot_mm(1), -95);
  auto scene = SimScene::FromLoadedRig(mine);
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_NE((*scene)->head(), nullptr);
  EXPECT_TRUE((*scene)->animated());
  // The default performance opens the jaw at 1.2 s: the user's jaw moves.
  const int64_t frame = static_cast<int64_t>(1.2 / (38 / 912.0));
  EXPECT_GT((*scene)->PoseAt(frame).expression[ExpressionIndex("jaw_open")], 0.9f);
  const TriangleMesh open = (*scene)->model()->PosedMesh((*scene)->PoseAt(frame));
  float moved = 0;
  for (size_t v = 0; v < open.positions.size(); ++v) {
    moved = std::max(moved, (open.positions[v] - (*scene)->head()->neutral().positions[v]).norm());
  }
  EXPECT_GT(moved, 5);  // mm
  // A missing albedo is a validation error naming the field.
  subject->mutable_asset()->clear_albedo();
  const auto errors = ValidateRig(mine.rig, dir);
  ASSERT_FALSE(errors.empty());
  EXPECT_EQ(errors[0].path, "sim.subject.asset.albedo");
}

TEST(HeadAssetTest, BadFilesAreNamed) {
  const std::string dir = ::testing::TempDir() + "/head-asset-bad";
  HeadAssetFiles files = WriteAsset(dir);
  files.blendshapes = {{"grin", dir + "/jaw.obj"}};
  auto bad = HeadModel::FromAsset(files);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("\"grin\" is not an expression"));

  ASSERT_TRUE(WriteObj(dir + "/other.obj", HeadModel::Procedural(3, 32)->neutral()).ok());
  files.blendshapes = {{"pucker", dir + "/other.obj"}};
  bad = HeadModel::FromAsset(files);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("other.obj does not have the topology of"));

  files.blendshapes.clear();
  files.albedo = dir + "/nowhere.png";
  bad = HeadModel::FromAsset(files);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("sim.subject.asset.albedo"));
  EXPECT_THAT(bad.status().message(), HasSubstr("nowhere.png"));
}

}  // namespace
}  // namespace stage::sim
