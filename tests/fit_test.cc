// The template fit as a stage (docs/assets.md#the-fit): a performer of other proportions (identity 7) through three
// frames of the default performance, its true meshes written as a take's surfaces; the batch command and the library
// write the same bytes; the fitted mesh lies on the surface; the geometry map and pose come back; the mesh opens in
// Open3D's Python module with its texture coordinates.
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <sstream>

#include "absl/strings/str_format.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/mesh.h"
#include "stage/processing/evaluate_mvs.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/uv_geometry.h"
#include "stage/sim/head.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

TEST(FitStageTest, TheCommandAndTheLibraryFitEveryFrameAndWriteTheSameBytes) {
  TempDir take;
  const auto performer = sim::HeadModel::Procedural(1, 256, sim::HeadShape::Drawn(7));
  std::vector<TriangleMesh> truths;
  for (int frame = 0; frame < 3; ++frame) {
    truths.push_back(performer->PosedMesh(sim::Performance::Default().At(0.2 * frame)));
    const std::string dir = absl::StrFormat("%s/ground_truth/frame-%06d", take.path(), frame);
    std::filesystem::create_directories(dir);
    ASSERT_TRUE(WriteObj(dir + "/mesh.obj", truths.back()).ok());
  }
  CommandResult none = RunCommand({"stage-process", "fit", "--take", take.path()}, std::chrono::seconds(60));
  EXPECT_EQ(none.exit.exit_code, 2);
  EXPECT_THAT(none.err, HasSubstr(take.path() + "/derived/mvs: no surfaces to fit (run the mvs stage first)"));

  CommandResult batch = RunCommand({"stage-process", "fit", "--take", take.path(), "--surface", "ground_truth",
                                    "--output", take.path() + "/derived/fit-batch", "--json"},
                                   std::chrono::seconds(600));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  EXPECT_EQ(nlohmann::json::parse(batch.out)["frames"], 3);
  processing::FitJob job;
  job.take_dir = take.path();
  job.surface = processing::GeometrySpec::Parse("ground_truth");
  job.output_dir = take.path() + "/derived/fit-library";
  std::vector<int64_t> seen;
  auto library = processing::RunFit(job, [&](const processing::JobProgress& p) { seen.push_back(p.done); });
  ASSERT_TRUE(library.ok()) << library.status();
  EXPECT_EQ(seen, (std::vector<int64_t>{0, 1, 2, 3}));
  const auto a = FilesUnder(take.path() + "/derived/fit-batch"), b = FilesUnder(take.path() + "/derived/fit-library");
  ASSERT_EQ(a.size(), 1 + 3 * 4u);  // run.json; per frame mesh, geometry map, pose, metrics
  for (const auto& [name, bytes] : a) {
    ASSERT_EQ(b.count(name), 1u) << name;
    EXPECT_TRUE(bytes == b.at(name)) << name << " differs between the command and the library";
  }

  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  for (int frame = 0; frame < 3; ++frame) {
    const std::string dir = absl::StrFormat("%s/derived/fit-batch/frame-%06d", take.path(), frame);
    auto fitted = ReadObj(dir + "/mesh.obj");
    ASSERT_TRUE(fitted.ok()) << fitted.status();
    ASSERT_EQ(fitted->positions.size(), face->mesh.positions.size());
    ASSERT_EQ(fitted->uvs.size(), face->mesh.uvs.size());
    // On the performer's surface: RMS over the skin under 0.25 mm (measured 0.06-0.17 mm through the performance).
    processing::SurfaceDistance truth(truths[static_cast<size_t>(frame)]);
    double sum = 0;
    int n = 0;
    for (size_t v = 0; v < fitted->positions.size(); ++v) {
      if (face->regions[v] != processing::FaceRegion::kSkin) continue;
      const double d = truth.Distance(fitted->positions[v]);
      sum += d * d;
      ++n;
    }
    EXPECT_LT(std::sqrt(sum / n), 0.25) << frame;
    auto map = processing::ReadGeometryMap(dir + "/geometry_map.exr");
    ASSERT_TRUE(map.ok()) << map.status();
    EXPECT_EQ(map->size, 256);
    EXPECT_GT(map->Count(processing::TexelState::kCovered), 256 * 256 * 9 / 10);
    const nlohmann::json pose = nlohmann::json::parse(ReadFile(dir + "/pose.json"));
    EXPECT_EQ(pose["stage_from_head"].size(), 16u);
    EXPECT_NEAR(pose["scale"].get<double>(), 1, 0.1);
  }

  // The evaluation against the truth, as a command: the library's figures of the same frames.
  CommandResult evaluated =
      RunCommand({"stage-process", "evaluate", "fit", "--take", take.path(), "--fit", "derived/fit-batch", "--json"},
                 std::chrono::seconds(120));
  ASSERT_EQ(evaluated.exit.exit_code, 0) << evaluated.err;
  const nlohmann::json report = nlohmann::json::parse(evaluated.out);
  EXPECT_EQ(report["fit_surface"], "ground_truth");
  ASSERT_EQ(report["frames"].size(), 3u);
  for (int frame = 0; frame < 3; ++frame) {
    auto fitted = ReadObj(absl::StrFormat("%s/derived/fit-batch/frame-%06d/mesh.obj", take.path(), frame));
    ASSERT_TRUE(fitted.ok());
    processing::TemplateFit f;
    f.positions = fitted->positions;
    auto direct = processing::EvaluateFit(*face, f, truths[static_cast<size_t>(frame)]);
    ASSERT_TRUE(direct.ok());
    const nlohmann::json& skin = report["frames"][static_cast<size_t>(frame)]["fit"]["skin"];
    EXPECT_EQ(skin["vertices"].get<int64_t>(), direct->skin.vertices);
    EXPECT_NEAR(skin["rmse_mm"].get<double>(), direct->skin.rmse_mm, 1e-4);  // the truth read back from OBJ
    EXPECT_NEAR(skin["sliding_rmse_mm"].get<double>(), direct->skin.sliding_rmse_mm, 1e-4);
    EXPECT_LT(skin["surface_rmse_mm"].get<double>(), 0.25) << frame;
  }
  CommandResult no_fit =
      RunCommand({"stage-process", "evaluate", "fit", "--take", take.path()}, std::chrono::seconds(60));
  EXPECT_NE(no_fit.exit.exit_code, 0);
  EXPECT_THAT(no_fit.err, HasSubstr(take.path() + "/derived/fit: no results from frame 0 (run the fit first)"));

  // The fitted mesh in Open3D's Python module, with a texture coordinate for every corner of every triangle.
  CommandResult py = RunCommand({"/usr/bin/python3", "-c",
                                 "import sys, open3d as o3d, numpy as np\n"
                                 "m = o3d.io.read_triangle_mesh(sys.argv[1])\n"
                                 "print(len(m.vertices), len(m.triangles), len(m.triangle_uvs))\n",
                                 take.path() + "/derived/fit-batch/frame-000002/mesh.obj"},
                                std::chrono::seconds(120));
  ASSERT_EQ(py.exit.exit_code, 0) << py.err;
  std::istringstream got(py.out);
  size_t vertices = 0, triangles = 0, uvs = 0;
  got >> vertices >> triangles >> uvs;
  EXPECT_EQ(vertices, face->mesh.positions.size());
  EXPECT_EQ(triangles, face->mesh.triangles.size());
  EXPECT_EQ(uvs, 3 * face->mesh.triangles.size());
}

}  // namespace
}  // namespace stage::testing
