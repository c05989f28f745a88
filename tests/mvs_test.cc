// Multi-view stereo on the simulated stage, the three ways a user runs it: the stage's worker (stagectl process
// --stage mvs), the batch command (stage-process mvs) and the library call write the same bytes; the mesh is checked
// against the ground truth with bounds for the reduced render scale; it opens in Open3D's Python module; photometric
// stereo takes it as its geometry (--geometry mvs) and is compared with the same maps on the true geometry.
#include "stage/processing/mvs.h"

#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <sstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/mesh.h"
#include "stage/processing/evaluate_mvs.h"
#include "test_support.h"

namespace stage::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

// Photometric stereo's evaluation of `results`: the mean and median angle of the diffuse normals, degrees.
std::pair<double, double> DiffuseNormalError(const std::string& take, const std::string& results) {
  CommandResult eval =
      RunCommand({"stage-process", "evaluate", "photometric", "--take", take, "--results", results, "--json"},
                 std::chrono::seconds(120));
  EXPECT_EQ(eval.exit.exit_code, 0) << eval.err;
  const nlohmann::json j = nlohmann::json::parse(eval.out, nullptr, false);
  for (const auto& m : j["maps"]) {
    if (m["map"] == "diffuse normal") return {m["mean"].get<double>(), m["median"].get<double>()};
  }
  ADD_FAILURE() << "no diffuse normal in " << eval.out;
  return {0, 0};
}

using MvsTest = SimulatedStageTest;

TEST_F(MvsTest, TheStageReconstructsTheHeadAndPhotometricStereoStandsOnIt) {
  TempDir root;
  // Render scale 0.125: 324 x 256 machine-vision images, a pixel ~1.1 mm on the head.
  ASSERT_NO_FATAL_FAILURE(StartStage({"--set", "sim.render_scale=0.125", "--take-root", root.path()}));
  const std::string endpoints = run_dir_.path() + "/endpoints.json";
  CommandResult capture = RunCommand({"stagectl", "--endpoints", endpoints, "capture", "--frames", "1", "--json"},
                                     std::chrono::seconds(600));
  ASSERT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  const std::string id = take["take_id"], dir = take["dir"];

  // Photometric stereo cannot stand on a reconstruction that is not there yet: it says where it looked.
  CommandResult early = RunCommand({"stage-process", "photometric", "--take", dir}, std::chrono::seconds(60));
  EXPECT_NE(early.exit.exit_code, 0);
  EXPECT_THAT(early.err, HasSubstr(dir + "/derived/mvs"));

  CommandResult worker = RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage", "mvs",
                                     "--calibration", "ground_truth", "--json"},
                                    std::chrono::seconds(600));
  ASSERT_EQ(worker.exit.exit_code, 0) << worker.err;
  EXPECT_EQ(nlohmann::json::parse(worker.out)["output_dir"], dir + "/derived/mvs");
  CommandResult batch = RunCommand({"stage-process", "mvs", "--take", dir, "--calibration", "ground_truth", "--output",
                                    dir + "/derived/mvs-batch", "--threads", "1"},
                                   std::chrono::seconds(600));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  EXPECT_THAT(batch.out, HasSubstr("1 frame(s) reconstructed into " + dir + "/derived/mvs-batch"));
  processing::MvsJob job;
  job.take_dir = dir;
  job.calibration = "ground_truth";
  job.output_dir = dir + "/derived/mvs-library";
  auto library = processing::RunMvs(job);
  ASSERT_TRUE(library.ok()) << library.status();
  const auto a = FilesUnder(dir + "/derived/mvs"), b = FilesUnder(dir + "/derived/mvs-batch"),
             c = FilesUnder(dir + "/derived/mvs-library");
  EXPECT_EQ(a.size(), 52u);  // mesh, metrics, run.json, 24 depth maps, 24 silhouettes and their cameras
  EXPECT_TRUE(a.count("frame-000000/depth/mv-05.exr"));
  EXPECT_TRUE(a.count("frame-000000/silhouette/mv-05.png"));
  EXPECT_TRUE(a.count("frame-000000/silhouette/cameras.json"));
  for (const auto& [path, bytes] : a) {
    if (path == "run.json") continue;
    EXPECT_TRUE(b.count(path) && b.at(path) == bytes) << path << ": the worker's and the batch's differ";
    EXPECT_TRUE(c.count(path) && c.at(path) == bytes) << path << ": the worker's and the library's differ";
  }

  // The face template fitted to the mesh on the stage's worker and by the batch command: the same bytes (the
  // library's own run is in stage_fit_integration_test); the fit lies on the reconstruction.
  CommandResult fit_worker = RunCommand(
      {"stagectl", "--endpoints", endpoints, "process", id, "--stage", "fit", "--json"}, std::chrono::seconds(600));
  ASSERT_EQ(fit_worker.exit.exit_code, 0) << fit_worker.err;
  EXPECT_EQ(nlohmann::json::parse(fit_worker.out)["output_dir"], dir + "/derived/fit");
  CommandResult fit_batch = RunCommand({"stage-process", "fit", "--take", dir, "--output", dir + "/derived/fit-batch"},
                                       std::chrono::seconds(600));
  ASSERT_EQ(fit_batch.exit.exit_code, 0) << fit_batch.err;
  const auto fa = FilesUnder(dir + "/derived/fit"), fb = FilesUnder(dir + "/derived/fit-batch");
  EXPECT_EQ(fa.size(), 5u);  // run.json; mesh, geometry map, pose, metrics
  for (const auto& [path, bytes] : fa) {
    EXPECT_TRUE(fb.count(path) && fb.at(path) == bytes) << path << ": the worker's and the batch's fits differ";
  }
  const nlohmann::json fit_metrics = nlohmann::json::parse(fa.at("frame-000000/metrics.json"));
  std::printf("template fit on the MVS mesh: %d of %d vertices matched, %.3f mm rms to the surface\n",
              fit_metrics["matched_vertices"].get<int>(), fit_metrics["template_vertices"].get<int>(),
              fit_metrics["rms_to_surface_mm"].get<double>());
  EXPECT_GT(fit_metrics["matched_vertices"].get<int>(), fit_metrics["template_vertices"].get<int>() / 2);
  // The fit against where every template vertex belongs on the true head. At this render scale the reconstruction is
  // ~1.1 mm off the skin (RMSE, below), which the fit follows along the normal; along the surface the model holds the
  // skin in place. Measured (2026-11-29): skin RMSE 1.5 mm, sliding 1.0 mm; without the model (--model-iterations
  // 0) sliding 3.5 mm, p99 13 mm.
  CommandResult fit_eval =
      RunCommand({"stage-process", "evaluate", "fit", "--take", dir, "--json"}, std::chrono::seconds(120));
  ASSERT_EQ(fit_eval.exit.exit_code, 0) << fit_eval.err;
  const nlohmann::json skin = nlohmann::json::parse(fit_eval.out)["frames"][0]["fit"]["skin"];
  std::printf("template fit against the truth: skin RMSE %.3f mm, along the normal %.3f, sliding %.3f (p99 %.3f)\n",
              skin["rmse_mm"].get<double>(), skin["surface_rmse_mm"].get<double>(),
              skin["sliding_rmse_mm"].get<double>(), skin["sliding_p99_mm"].get<double>());
  EXPECT_LT(skin["sliding_rmse_mm"].get<double>(), 1.5);
  EXPECT_LT(skin["sliding_p99_mm"].get<double>(), 3.5);
  EXPECT_LT(skin["rmse_mm"].get<double>(), 2.0);

  // Against the truth. Bounds for render scale 0.125 (measured on the face, printed below: RMSE 1.07 mm, median
  // 0.43 mm, 81 % within 1 mm, 78 % covered); the figures at half and full resolution are in docs/geometry.md.
  processing::MvsEvaluateOptions eval;
  eval.take_dir = dir;
  auto e = processing::EvaluateMvs(eval);
  ASSERT_TRUE(e.ok()) << e.status();
  const processing::MvsRegionError& face = e->regions[static_cast<int>(processing::HeadRegion::kFace)];
  EXPECT_GT(face.vertices, 20000);
  EXPECT_LT(face.rmse_mm, 1.5);
  EXPECT_LT(face.median_mm, 0.6);
  EXPECT_GT(face.completeness, 0.7);
  EXPECT_GT(face.coverage, 0.65) << "the face has holes";
  std::printf("face: RMSE %.3f mm, median %.3f mm, within 1 mm %.1f %%, covered %.1f %%\n", face.rmse_mm,
              face.median_mm, 100 * face.completeness, 100 * face.coverage);
  EXPECT_GT(e->regions[static_cast<int>(processing::HeadRegion::kEyes)].seen_area_mm2, 0) << "no eyes reported";
  EXPECT_GT(e->regions[static_cast<int>(processing::HeadRegion::kMouth)].vertices, 0) << "no mouth reported";
  EXPECT_LT(e->unseen_vertices, e->vertices / 20);
  eval.within_mm = 3;
  auto holes = processing::EvaluateMvs(eval);
  ASSERT_TRUE(holes.ok()) << holes.status();
  EXPECT_GT(holes->regions[static_cast<int>(processing::HeadRegion::kFace)].completeness, 0.93) << "the face has holes";
  CommandResult table = RunCommand({"stage-process", "evaluate", "mvs", "--take", dir}, std::chrono::seconds(120));
  ASSERT_EQ(table.exit.exit_code, 0) << table.err;
  EXPECT_THAT(table.out, HasSubstr("face"));

  // The mesh in Open3D's Python module, as users open it.
  auto mesh = ReadObj(dir + "/derived/mvs/frame-000000/mesh.obj");
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  Eigen::Vector3f lo = mesh->positions[0], hi = lo;
  for (const auto& p : mesh->positions) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  CommandResult py = RunCommand({"/usr/bin/python3", "-c",
                                 "import sys, open3d as o3d, numpy as np\n"
                                 "m = o3d.io.read_triangle_mesh(sys.argv[1])\n"
                                 "v = np.asarray(m.vertices)\n"
                                 "print(len(v), len(m.triangles), *v.min(0), *v.max(0))\n",
                                 dir + "/derived/mvs/frame-000000/mesh.obj"},
                                std::chrono::seconds(120));
  ASSERT_EQ(py.exit.exit_code, 0) << py.err;
  std::istringstream got(py.out);
  size_t vertices = 0, triangles = 0;
  float b3[6];
  got >> vertices >> triangles >> b3[0] >> b3[1] >> b3[2] >> b3[3] >> b3[4] >> b3[5];
  // Open3D's reader merges the odd pair of vertices that print the same at 0.1 um.
  EXPECT_NEAR(static_cast<double>(vertices), static_cast<double>(mesh->positions.size()),
              1e-3 * mesh->positions.size());
  EXPECT_EQ(triangles, mesh->triangles.size());
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(b3[k], lo[k], 1e-3);
    EXPECT_NEAR(b3[3 + k], hi[k], 1e-3);
  }

  // Photometric stereo on the reconstruction, beside the same on the true geometry and on none (per-pixel solver).
  for (const std::string geometry : {"mvs", "ground_truth", "none"}) {
    std::vector<std::string> args = {"stage-process", "photometric",  "--take",   dir,
                                     "--calibration", "ground_truth", "--output", dir + "/derived/ps-" + geometry,
                                     "--exact"};
    if (geometry != "mvs") args.insert(args.end(), {"--geometry", geometry});  // mvs: the default
    CommandResult run = RunCommand(args, std::chrono::seconds(600));
    ASSERT_EQ(run.exit.exit_code, 0) << run.err;
  }
  // The pixels placed beyond the mesh's edge were kept inside the frame's visual hull (the 24 views' silhouettes).
  for (const std::string camera : {"hs-1", "hs-2", "hs-3"}) {
    const nlohmann::json unit =
        nlohmann::json::parse(FilesUnder(dir + "/derived/ps-mvs/frame-000000/" + camera).at("metrics.json"));
    EXPECT_EQ(unit["geometry_hull_views"], 24) << camera;
    EXPECT_GT(unit["geometry_hull_bounded_pixels"].get<int64_t>(), unit["geometry_filled_pixels"].get<int64_t>() / 2)
        << camera;
  }
  const auto on_mvs = DiffuseNormalError(dir, dir + "/derived/ps-mvs");
  const auto on_truth = DiffuseNormalError(dir, dir + "/derived/ps-ground_truth");
  const auto on_none = DiffuseNormalError(dir, dir + "/derived/ps-none");
  std::printf(
      "diffuse normals, mean and median degrees: on MVS %.2f, %.2f; on the truth %.2f, %.2f; on none %.2f, %.2f\n",
      on_mvs.first, on_mvs.second, on_truth.first, on_truth.second, on_none.first, on_none.second);
  // Measured at this scale (mean, median degrees): on MVS 3.28, 1.92 (3.57, 2.04 before the placed points were kept
  // inside the visual hull; 3.85, 2.09 before the pixels beyond the mesh's edge were placed again along the solved
  // normals; 4.3, 2.5 before they were placed at all and rays through its
  // holes left out); on the truth 2.2, 1.4; on none 6.0, 5.3. The
  // reconstruction's error is a millimetre here (docs/geometry.md has half resolution).
  EXPECT_LT(on_mvs.second, on_none.second) << "the reconstruction does not help photometric stereo";
  EXPECT_LT(on_mvs.first, 2.0 * on_truth.first);
}

}  // namespace
}  // namespace stage::testing
