// Ground truth files against what the subject is: a sphere's depth and normals against the closed form; the head's
// UV position map covers the skin and lies on the posed mesh; the pose file carries the performance's weights.
#include "stage/sim/ground_truth.h"

#include <Eigen/Geometry>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "gtest/gtest.h"
#include "stage/common/rig.h"

namespace stage::sim {
namespace {

std::shared_ptr<const SimScene> Scene(std::vector<std::string> overrides) {
  auto loaded = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(loaded.ok());
  overrides.push_back("sim.render_scale=0.05");
  auto rig = ApplyRigOverrides(*loaded, overrides);
  EXPECT_TRUE(rig.ok()) << rig.status();
  auto scene = SimScene::FromLoadedRig(*rig);
  EXPECT_TRUE(scene.ok()) << scene.status();
  return *scene;
}

TEST(GroundTruthTest, TheCamerasSitOffTheRigAsTheSeedSaysAndTheTruthSaysWhere) {
  auto scene = Scene({"sim.subject.kind=sphere"});
  const std::string dir = ::testing::TempDir() + "/gt-cameras";
  ASSERT_TRUE(WriteGroundTruth(*scene, dir, {.cameras = {"hs-2"}}).ok());
  auto truth = ReadCameraCalibration(dir + "/cameras.json");
  ASSERT_TRUE(truth.ok()) << truth.status();
  EXPECT_EQ(truth->source, "simulator truth");
  ASSERT_EQ(truth->cameras.size(), static_cast<size_t>(scene->rig().cameras_size()));
  // Every camera renders as its true model says (scaled to the render), and the truth differs from the rig's model by
  // about the defaults: ~2 mm, ~0.3 degrees, ~0.5 %, a few pixels (27 draws: loose bounds on their RMS).
  double position2 = 0, angle2 = 0, focal2 = 0;
  for (int i = 0; i < scene->rig().cameras_size(); ++i) {
    const CameraModel* t = truth->Find(scene->rig().cameras(i).id());
    ASSERT_NE(t, nullptr);
    auto nominal = CameraModel::FromConfig(scene->rig().cameras(i), 1.0);
    ASSERT_TRUE(nominal.ok());
    const CameraModel rendered = t->Scaled(scene->rig().sim().render_scale());
    EXPECT_DOUBLE_EQ(rendered.fx(), scene->camera(i).fx());
    EXPECT_EQ(rendered.position(), scene->camera(i).position());
    position2 += (t->position() - nominal->position()).squaredNorm();
    const Eigen::AngleAxisd turn(t->rotation() * nominal->rotation().transpose());
    angle2 += std::pow(turn.angle() * 180 / M_PI, 2);
    focal2 += std::pow(t->fx() / nominal->fx() - 1, 2);
  }
  const double n = scene->rig().cameras_size();
  EXPECT_NEAR(std::sqrt(position2 / n), 2.0, 0.8);
  EXPECT_NEAR(std::sqrt(angle2 / n), 0.3, 0.12);
  EXPECT_NEAR(std::sqrt(focal2 / n), 0.005, 0.002);
  // The same seed places them the same; another seed elsewhere; scale 0 where the rig says.
  EXPECT_EQ(Scene({"sim.subject.kind=sphere"})->true_cameras().cameras[3].model.position(),
            truth->cameras[3].model.position());
  EXPECT_NE(Scene({"sim.subject.kind=sphere", "sim.seed=2"})->true_cameras().cameras[3].model.position(),
            truth->cameras[3].model.position());
  auto nominal = Scene({"sim.subject.kind=sphere", "sim.camera_deviation.scale=0"});
  auto model3 = CameraModel::FromConfig(nominal->rig().cameras(3), 1.0);
  EXPECT_EQ(nominal->true_cameras().cameras[3].model.position(), model3->position());
  EXPECT_EQ(nominal->true_cameras().cameras[3].model.rotation(), model3->rotation());
}

TEST(GroundTruthTest, ASpheresDepthAndNormalsAreTheClosedForm) {
  auto scene = Scene({"sim.subject.kind=sphere", "sim.subject.size_mm=100"});
  const std::string dir = ::testing::TempDir() + "/gt-sphere";
  ASSERT_TRUE(WriteGroundTruth(*scene, dir, {.cameras = {"hs-2"}}).ok());
  setenv("OPENCV_IO_ENABLE_OPENEXR", "1", 0);
  const cv::Mat depth = cv::imread(dir + "/frame-000000/hs-2/depth.exr", cv::IMREAD_UNCHANGED);
  const cv::Mat normal = cv::imread(dir + "/frame-000000/hs-2/normal_world.exr", cv::IMREAD_UNCHANGED);
  const cv::Mat mask = cv::imread(dir + "/frame-000000/hs-2/mask.png", cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(depth.empty());
  ASSERT_FALSE(normal.empty());
  const CameraModel& cam = scene->camera(scene->CameraIndex("hs-2"));
  ASSERT_EQ(depth.cols, cam.width());
  const std::vector<Eigen::Vector3f> rays = cam.PixelRays();
  int covered = 0;
  double worst_depth = 0, worst_normal = 0;
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      if (mask.at<uint8_t>(y, x) == 0) continue;
      ++covered;
      // The point the ground truth says the pixel sees must lie on the sphere, and its normal point from the centre.
      const Eigen::Vector3d d = rays[static_cast<size_t>(y) * depth.cols + x].cast<double>();
      const double along = depth.at<float>(y, x) / d.dot(cam.optical_axis());
      const Eigen::Vector3d p = cam.position() + along * d;
      worst_depth = std::max(worst_depth, std::abs(p.norm() - 100));
      const cv::Vec3f n = normal.at<cv::Vec3f>(y, x);  // stored B, G, R = z, y, x
      worst_normal = std::max(worst_normal, (Eigen::Vector3d(n[2], n[1], n[0]) - p.normalized()).norm());
    }
  }
  EXPECT_GT(covered, 500);
  EXPECT_LT(worst_depth, 0.01);   // mm
  EXPECT_LT(worst_normal, 1e-4);  // unit vectors
}

TEST(GroundTruthTest, TheHeadsUvMapLiesOnItsMeshAndThePoseIsRecorded) {
  auto scene = Scene({});
  ASSERT_NE(scene->head(), nullptr);
  const std::string dir = ::testing::TempDir() + "/gt-head";
  // Frame 6 of the default performance: 0.25 s in, on the way to a brow raise.
  ASSERT_TRUE(WriteGroundTruth(*scene, dir, {.first_frame = 6, .last_frame = 7, .cameras = {"hs-2"}}).ok());
  std::ifstream pose_file(dir + "/frame-000006/pose.json");
  const auto pose = nlohmann::json::parse(pose_file);
  const HeadPose expected = scene->PoseAt(6);
  EXPECT_GT(expected.expression[ExpressionIndex("brow_raise")], 0.3f);
  EXPECT_FLOAT_EQ(pose["expression"]["brow_raise"].get<float>(), expected.expression[ExpressionIndex("brow_raise")]);

  const TriangleMesh mesh = scene->head()->PosedMesh(expected);
  const std::vector<float> uv = UvPositionMap(mesh, 256);
  int covered = 0;
  double worst = 0;
  MeshSubject subject(mesh, nullptr);
  for (int t = 0; t < 256 * 256; t += 37) {
    if (uv[4 * t + 3] == 0) continue;
    ++covered;
    // The rows at the poles are each one point, where every triangle of the fan meets: a ray aimed at a vertex may
    // pass between its triangles.
    if (t / 256 == 0 || t / 256 == 255) continue;
    const Eigen::Vector3f p(uv[4 * t], uv[4 * t + 1], uv[4 * t + 2]);
    // A ray from outside towards the point meets the surface there (or in front of it: a fold may hide it).
    const Eigen::Vector3f from = p + 300 * (p - Eigen::Vector3f(0, 0, 0)).normalized();
    const Hit h = subject.Intersect(from, (p - from).normalized());
    ASSERT_TRUE(h.hit);
    worst = std::max(worst, static_cast<double>(std::max(0.0f, h.t - (p - from).norm())));
  }
  EXPECT_GT(covered, 256 * 256 / 37 * 95 / 100);  // the skin's UV layout covers the whole square
  EXPECT_LT(worst, 0.05);                         // mm behind the surface at most
  EXPECT_TRUE(std::ifstream(dir + "/frame-000006/mesh.obj").good());
  EXPECT_FALSE(cv::imread(dir + "/frame-000006/uv_position.exr", cv::IMREAD_UNCHANGED).empty());
}

// The truth's textures in UV are what the renderer shades with: a ray at a texel's point meets the posed subject with
// the texel's albedo and, turned by the pose, its shading normal (the wrinkles the brow raise brings included).
TEST(GroundTruthTest, TheHeadsUvTexturesAreWhatTheRendererShadesWith) {
  auto scene = Scene({});
  const std::string dir = ::testing::TempDir() + "/gt-textures";
  ASSERT_TRUE(WriteGroundTruth(*scene, dir,
                               {.first_frame = 6,
                                .last_frame = 7,
                                .uv_size = 512,
                                .camera_maps = false,
                                .meshes = false,
                                .uv_textures = true})
                  .ok());
  const std::string frame = dir + "/frame-000006";
  const cv::Mat position = cv::imread(frame + "/uv_position.exr", cv::IMREAD_UNCHANGED);
  const cv::Mat albedo = cv::imread(frame + "/uv_albedo.exr", cv::IMREAD_UNCHANGED);
  const cv::Mat material = cv::imread(frame + "/uv_material.exr", cv::IMREAD_UNCHANGED);
  const cv::Mat normal = cv::imread(frame + "/uv_normal.exr", cv::IMREAD_UNCHANGED);
  for (const cv::Mat* m : {&position, &albedo, &material, &normal}) {
    ASSERT_EQ(m->type(), CV_32FC4);
    ASSERT_EQ(m->rows, 512);
  }
  const HeadPose pose = scene->PoseAt(6);
  const Eigen::Matrix3f turn = PoseRotation(pose);
  const auto subject = scene->SubjectAt(6);
  int compared = 0;
  double worst_angle = 0, worst_albedo = 0, worst_specular = 0;
  for (int y = 120; y < 360; y += 7) {  // the face: v from 0.77 down to 0.30, u about 0.5
    for (int x = 180; x < 332; x += 7) {
      const cv::Vec4f p4 = position.at<cv::Vec4f>(y, x), n4 = normal.at<cv::Vec4f>(y, x);
      if (p4[3] < 1) continue;
      ASSERT_EQ(n4[3], 1.f);
      const Eigen::Vector3f p(p4[2], p4[1], p4[0]), n(n4[2], n4[1], n4[0]);  // OpenCV's B, G, R
      ASSERT_NEAR(n.norm(), 1, 1e-4);
      const Eigen::Vector3f out = turn * n;
      const Eigen::Vector3f from = p + 40 * out;
      const Hit h = subject->Intersect(from, (p - from).normalized());
      if (!h.hit || std::abs(h.t - 40) > 0.01f) continue;  // something nearer: another part of the face
      ++compared;
      worst_angle = std::max(worst_angle, std::acos(std::clamp<double>(h.normal.dot(out), -1, 1)) * 180 / M_PI);
      const cv::Vec4f a = albedo.at<cv::Vec4f>(y, x), m = material.at<cv::Vec4f>(y, x);
      worst_albedo =
          std::max(worst_albedo,
                   static_cast<double>((h.material.albedo - Eigen::Vector3f(a[2], a[1], a[0])).cwiseAbs().maxCoeff()));
      worst_specular = std::max(worst_specular, static_cast<double>(std::abs(h.material.specular - m[2])));
    }
  }
  EXPECT_GT(compared, 400);
  EXPECT_LT(worst_angle, 0.5) << "degrees";
  EXPECT_LT(worst_albedo, 2e-3);
  EXPECT_LT(worst_specular, 2e-4);
}

// A calibration take's truth: the true cameras and each frame's subject, no per-camera maps.
TEST(GroundTruthTest, TheSceneAloneWritesNoCameraMaps) {
  auto scene = Scene({"sim.subject.kind=charuco"});
  const std::string dir = ::testing::TempDir() + "/gt-scene";
  int calls = 0;
  GroundTruthOptions options{.first_frame = 2, .last_frame = 4, .camera_maps = false};
  options.progress = [&](int done, int total) {
    ++calls;
    EXPECT_LE(done, total);
  };
  ASSERT_TRUE(WriteGroundTruth(*scene, dir, options).ok());
  EXPECT_EQ(calls, 2);
  EXPECT_TRUE(std::ifstream(dir + "/cameras.json").good());
  for (const char* frame : {"/frame-000002", "/frame-000003"}) {
    std::ifstream pose_file(dir + frame + "/pose.json");
    ASSERT_TRUE(pose_file.good()) << frame;
    EXPECT_EQ(nlohmann::json::parse(pose_file)["board"]["corners_mm"].size(), scene->board()->corners().size());
    EXPECT_TRUE(std::ifstream(dir + frame + "/mesh.obj").good()) << frame;
    EXPECT_FALSE(std::filesystem::exists(dir + frame + "/hs-2")) << frame;
    EXPECT_FALSE(std::filesystem::exists(dir + frame + "/mv-01")) << frame;
  }
}

TEST(GroundTruthTest, RefusesEmptyFramesAndUnknownCameras) {
  auto scene = Scene({"sim.subject.kind=sphere"});
  EXPECT_FALSE(WriteGroundTruth(*scene, ::testing::TempDir(), {.first_frame = 3, .last_frame = 3}).ok());
  auto s = WriteGroundTruth(*scene, ::testing::TempDir(), {.cameras = {"hs-9"}});
  EXPECT_NE(s.message().find("hs-9"), std::string::npos) << s;
}

// A neural asset's long performance: every third frame, no meshes nor camera maps; each pose file says the head's
// frame (it takes the neutral-pose mesh with the frame's expression onto the posed mesh) and the sequence.
TEST(GroundTruthTest, ARangeOfMotionsFramesCarryTheirSequenceAndTheHeadsFrame) {
  auto scene = Scene({"sim.subject.performance=range_of_motion", "sim.subject.head_resolution=64"});
  const std::string dir = ::testing::TempDir() + "/gt-rom";
  std::filesystem::remove_all(dir);
  GroundTruthOptions options{
      .first_frame = 300, .last_frame = 307, .frame_step = 3, .uv_size = 64, .camera_maps = false, .meshes = false};
  ASSERT_TRUE(WriteGroundTruth(*scene, dir, options).ok());
  for (int64_t frame : {300, 303, 306}) {
    const std::string frame_dir = dir + "/frame-000" + std::to_string(frame);
    std::ifstream pose_file(frame_dir + "/pose.json");
    ASSERT_TRUE(pose_file.good()) << frame;
    const auto pose = nlohmann::json::parse(pose_file);
    EXPECT_EQ(pose["sequence"].get<std::string>(), scene->SequenceAt(frame));
    EXPECT_FALSE(pose["sequence"].get<std::string>().empty());
    EXPECT_FALSE(std::filesystem::exists(frame_dir + "/mesh.obj"));
    EXPECT_TRUE(std::filesystem::exists(frame_dir + "/uv_position.exr"));
    Eigen::Matrix4f m;
    for (int i = 0; i < 16; ++i) m(i / 4, i % 4) = pose["stage_from_head"][static_cast<size_t>(i)].get<float>();
    HeadPose unmoved = scene->PoseAt(frame);
    const TriangleMesh posed = scene->head()->PosedMesh(unmoved);
    unmoved.rotation_deg.setZero();
    unmoved.translation_mm.setZero();
    const TriangleMesh head = scene->head()->PosedMesh(unmoved);
    double worst = 0;
    for (size_t v = 0; v < head.positions.size(); ++v) {
      const Eigen::Vector3f p = m.topLeftCorner<3, 3>() * head.positions[v] + m.topRightCorner<3, 1>();
      worst = std::max(worst, static_cast<double>((p - posed.positions[v]).norm()));
    }
    EXPECT_LT(worst, 1e-3) << frame;
  }
  for (int64_t frame : {301, 302, 304}) {
    EXPECT_FALSE(std::filesystem::exists(dir + "/frame-000" + std::to_string(frame))) << frame;
  }
  // The head moves in this performance: the frames' poses differ.
  EXPECT_NE(scene->PoseAt(300).rotation_deg, scene->PoseAt(306).rotation_deg);
}

}  // namespace
}  // namespace stage::sim
