// A user's own head from files: OBJ blendshapes move the mesh as the weights say, the images give the material (sRGB
// albedo decoded, specular scaled, tangent-space normals tilting the shading normal by their angle), the rig wires it
// into the scene, and bad files are refused with the file or expression named.
#include <sys/wait.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/sim/head.h"
#include "stage/sim/scene.h"

namespace stage::sim {
namespace {

using ::testing::AllOf;
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

namespace stage::sim {
namespace {

// The decoded maps are shared between processes: the first process to load an asset writes them to the cache, every
// other one maps that file (one copy in the page cache for a whole stage), and what they sample is the same.
TEST(HeadAssetTest, ProcessesShareOneDecodedCopyOfTheMaps) {
  const std::string dir = ::testing::TempDir() + "/head-asset-cache";
  std::filesystem::remove_all(dir);
  const std::string cache = dir + "/cache";
  setenv("FASTAGE_CACHE_DIR", cache.c_str(), 1);
  const HeadAssetFiles files = WriteAsset(dir + "/asset");
  // Another process loads it first (a camera node of the stage).
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    auto head = HeadModel::FromAsset(files);
    _exit(head.ok() && (*head)->maps_origin() != "decoded" ? 0 : 3);
  }
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  std::vector<std::filesystem::path> written;
  for (const auto& e : std::filesystem::directory_iterator(cache)) {
    if (e.path().extension() == ".bin") written.push_back(e.path());
  }
  ASSERT_EQ(written.size(), 1u);
  // This process maps the file the other one wrote, and samples what decoding gives.
  auto head = HeadModel::FromAsset(files);
  ASSERT_TRUE(head.ok()) << head.status();
  EXPECT_EQ((*head)->maps_origin(), written[0].string());
  const SurfaceSample left = (*head)->Surface({0.2f, 0.5f}, 0, {});
  EXPECT_NEAR(left.material.albedo.x(), SrgbToLinear(200 / 255.0f), 1e-6);
  EXPECT_NEAR(left.material.specular, 0.3f * files.specular_scale, 1e-6);
  // A changed image is another cache entry, not the stale one.
  cv::Mat albedo(32, 64, CV_8UC3, cv::Scalar(10, 20, 30));
  std::this_thread::sleep_for(std::chrono::milliseconds(10));  // a modification time of its own
  ASSERT_TRUE(cv::imwrite(files.albedo, albedo));
  auto changed = HeadModel::FromAsset(files);
  ASSERT_TRUE(changed.ok()) << changed.status();
  EXPECT_NE((*changed)->maps_origin(), written[0].string());
  EXPECT_NEAR((*changed)->Surface({0.2f, 0.5f}, 0, {}).material.albedo.x(), SrgbToLinear(30 / 255.0f), 1e-6);
  unsetenv("FASTAGE_CACHE_DIR");
}

}  // namespace
}  // namespace stage::sim

namespace stage::sim {
namespace {

// Writes `text` to `path`.
void Write(const std::string& path, const std::string& text) { std::ofstream(path) << text; }

// A scan laid out in UV tiles (one a material) is refused, saying which tiles and how to pack them; it is never
// clamped to the tile's edge without a word.
TEST(HeadAssetTest, UvTilesAreRefusedWithHowToPackThem) {
  const std::string dir = ::testing::TempDir() + "/head-asset-udim";
  HeadAssetFiles files = WriteAsset(dir);
  auto mesh = ReadObj(files.neutral_obj);
  ASSERT_TRUE(mesh.ok());
  for (Eigen::Vector2f& uv : mesh->uvs) {
    if (uv.x() > 0.5f) uv.x() += 1;  // the right half of the face in tile 1002
  }
  ASSERT_TRUE(WriteObj(files.neutral_obj, *mesh).ok());
  files.blendshapes.clear();
  auto head = HeadModel::FromAsset(files);
  ASSERT_FALSE(head.ok());
  EXPECT_EQ(head.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(head.status().message()),
              AllOf(HasSubstr(files.neutral_obj + ": texture coordinates reach outside [0, 1]"),
                    HasSubstr("(UDIM 1001, 1002)"), HasSubstr("Pack the UVs into that one tile")));
}

// Transparent materials (an eye shell, an eyelash card) are left out, named; an open mesh says where its holes are; a
// closed, opaque one has nothing to say.
TEST(HeadAssetTest, TransparentMaterialsAreLeftOutAndHolesAreNamed) {
  const std::string dir = ::testing::TempDir() + "/head-asset-materials";
  HeadAssetFiles files = WriteAsset(dir);
  files.blendshapes.clear();
  auto closed = HeadModel::FromAsset(files);
  ASSERT_TRUE(closed.ok()) << closed.status();
  EXPECT_TRUE((*closed)->notes().empty()) << (*closed)->notes()[0];
  const size_t all = (*closed)->neutral().triangles.size();

  // The same mesh with its first 100 triangles as "EyeShell" (d 0.1) and the next 50 as "Lashes" (an alpha map).
  std::ifstream in(files.neutral_obj);
  std::string obj = "mtllib head.mtl\nusemtl Skin\n", line;
  int faces = 0;
  while (std::getline(in, line)) {
    if (line.rfind("f ", 0) == 0) {
      if (faces == 0) obj += "usemtl EyeShell\n";
      if (faces == 100) obj += "usemtl Lashes\n";
      if (faces == 150) obj += "usemtl Skin\n";
      ++faces;
    }
    obj += line + "\n";
  }
  Write(files.neutral_obj, obj);
  Write(dir + "/head.mtl",
        "newmtl Skin\nKd 0.8 0.6 0.5\nd 1\nnewmtl EyeShell\nd 0.1\nnewmtl Lashes\nmap_Kd lash.png\nmap_d "
        "lash_alpha.png\n");
  auto head = HeadModel::FromAsset(files);
  ASSERT_TRUE(head.ok()) << head.status();
  EXPECT_EQ((*head)->neutral().triangles.size(), all - 150);
  ASSERT_FALSE((*head)->notes().empty());
  EXPECT_THAT((*head)->notes()[0], AllOf(HasSubstr("left out 150 triangles of transparent materials"),
                                         HasSubstr("EyeShell (d 0.1, 100 triangles)"),
                                         HasSubstr("Lashes (map_d lash_alpha.png, 50 triangles)")));
  // Leaving them out opened the mesh where they were: said too.
  ASSERT_EQ((*head)->notes().size(), 2u);
  EXPECT_THAT((*head)->notes()[1], AllOf(HasSubstr("the mesh is open: "), HasSubstr("edges around (")));

  // Exporters' other spellings of opaque: Tr 1 (Metashape, MeshLab), an alpha map that is the diffuse texture itself.
  Write(dir + "/head.mtl",
        "newmtl Skin\nTr 1.000000\nnewmtl EyeShell\nTr 1.0\nnewmtl Lashes\nmap_Kd skin.png\nmap_d skin.png\n");
  auto opaque = HeadModel::FromAsset(files);
  ASSERT_TRUE(opaque.ok()) << opaque.status();
  EXPECT_EQ((*opaque)->neutral().triangles.size(), all);
  EXPECT_TRUE((*opaque)->notes().empty()) << (*opaque)->notes()[0];
  // A library that would leave out most of the mesh is not believed: kept, and said.
  Write(dir + "/head.mtl", "newmtl Skin\nd 0.5\nnewmtl EyeShell\nd 0.1\nnewmtl Lashes\nd 1\n");
  auto most = HeadModel::FromAsset(files);
  ASSERT_TRUE(most.ok()) << most.status();
  EXPECT_EQ((*most)->neutral().triangles.size(), all);
  ASSERT_EQ((*most)->notes().size(), 1u);
  EXPECT_THAT((*most)->notes()[0], HasSubstr("most of the mesh: kept and rendered opaque"));
}

}  // namespace
}  // namespace stage::sim
