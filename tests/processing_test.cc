// Processing a take of the simulated stage, the three ways a user runs it: the library call, the batch command
// (stage-process photometric) and the stage's ProcessingWorker through the controller (stagectl process). All three
// write the same bytes for the same frame; the evaluation reads them against the take's ground truth; bad requests
// are refused with the take, frame or path named.
#include <filesystem>
#include <nlohmann/json.hpp>
#include <sstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/processing/photometric_stage.h"
#include "test_support.h"

namespace stage::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;

using ProcessingTest = SimulatedStageTest;

TEST_F(ProcessingTest, TheLibraryTheCommandAndTheWorkerWriteTheSameBytes) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage({"--set", "sim.render_scale=0.05", "--take-root", root.path()}));
  const std::string endpoints = run_dir_.path() + "/endpoints.json";
  CommandResult capture = RunCommand({"stagectl", "--endpoints", endpoints, "capture", "--frames", "1", "--json"},
                                     std::chrono::seconds(300));
  ASSERT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  const std::string id = take["take_id"], dir = take["dir"];
  ASSERT_TRUE(fs::exists(dir + "/ground_truth/frame-000000/mesh.obj"));

  // The worker, through the controller: results in the take's derived/photometric.
  CommandResult worker = RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage", "photometric",
                                     "--geometry", "ground_truth", "--calibration", "ground_truth", "--json"},
                                    std::chrono::seconds(300));
  ASSERT_EQ(worker.exit.exit_code, 0) << worker.err;
  const nlohmann::json done = nlohmann::json::parse(worker.out);
  EXPECT_EQ(done["output_dir"], dir + "/derived/photometric");
  EXPECT_EQ(done["frames_done"], "3");  // one frame of three high-speed cameras
  EXPECT_THAT(worker.err, HasSubstr("3/3 camera frames"));
  // The catalog says which stages have results (the console's Takes page shows them).
  CommandResult takes = RunCommand({"stagectl", "--endpoints", endpoints, "takes", "--json"}, std::chrono::seconds(30));
  ASSERT_EQ(takes.exit.exit_code, 0) << takes.err;
  const nlohmann::json listed = nlohmann::json::parse(takes.out);
  nlohmann::json processed;
  for (const auto& t : listed["takes"]) {
    if (t["id"] == id) processed = t["processed"];
  }
  EXPECT_EQ(processed, nlohmann::json::array({"photometric"})) << takes.out;

  // The batch command and the library, each into a directory of its own.
  CommandResult batch = RunCommand({"stage-process", "photometric", "--take", dir, "--geometry", "ground_truth",
                                    "--calibration", "ground_truth", "--output", dir + "/derived/batch"},
                                   std::chrono::seconds(300));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  EXPECT_THAT(batch.out, HasSubstr("3 camera frame(s) processed into " + dir + "/derived/batch"));
  processing::PhotometricJob job;
  job.take_dir = dir;
  job.geometry = {processing::GeometrySource::kDirectory, "ground_truth"};
  job.calibration = "ground_truth";
  job.output_dir = dir + "/derived/library";
  job.options.threads = 1;  // the results do not depend on it
  std::vector<int64_t> seen;
  auto library = processing::RunPhotometric(job, [&](const processing::JobProgress& p) { seen.push_back(p.done); });
  ASSERT_TRUE(library.ok()) << library.status();
  EXPECT_EQ(seen, (std::vector<int64_t>{0, 1, 2, 3}));

  const auto a = FilesUnder(dir + "/derived/photometric"), b = FilesUnder(dir + "/derived/batch"),
             c = FilesUnder(dir + "/derived/library");
  // run.json; per camera 8 EXR maps, flags, 6 previews, contact sheet, metrics, and the geometry solved with
  ASSERT_EQ(a.size(), 1 + 3 * 19u);
  for (const std::string camera : {"hs-1", "hs-2", "hs-3"}) {
    for (const std::string file :
         {"diffuse_normal_world.exr", "diffuse_normal_camera.exr", "specular_normal_world.exr", "albedo.exr",
          "roughness.exr", "metrics.json", "contact_sheet.png", "geometry_depth.exr", "geometry_placed.png"}) {
      EXPECT_EQ(a.count("frame-000000/" + camera + "/" + file), 1u) << camera << "/" << file;
    }
  }
  for (const auto& [name, bytes] : a) {
    ASSERT_EQ(b.count(name), 1u) << name;
    ASSERT_EQ(c.count(name), 1u) << name;
    EXPECT_TRUE(bytes == b.at(name)) << name << " differs between the worker and the batch command";
    EXPECT_TRUE(bytes == c.at(name)) << name << " differs between the worker and the library";
  }

  // Without geometry the table-driven solver runs: the same bytes from the command (two threads) and the library (one).
  CommandResult fast = RunCommand({"stage-process", "photometric", "--take", dir, "--geometry", "none", "--output",
                                   dir + "/derived/fast-batch", "--threads", "2"},
                                  std::chrono::seconds(300));
  ASSERT_EQ(fast.exit.exit_code, 0) << fast.err;
  processing::PhotometricJob fast_job;
  fast_job.take_dir = dir;
  fast_job.geometry.source = processing::GeometrySource::kNone;
  fast_job.output_dir = dir + "/derived/fast-library";
  fast_job.options.threads = 1;
  ASSERT_TRUE(processing::RunPhotometric(fast_job).ok());
  const auto fa = FilesUnder(dir + "/derived/fast-batch"), fb = FilesUnder(dir + "/derived/fast-library");
  ASSERT_EQ(fa.size(), a.size() - 3 * 2);  // no geometry files
  for (const auto& [name, bytes] : fa) {
    ASSERT_EQ(fb.count(name), 1u) << name;
    EXPECT_TRUE(bytes == fb.at(name)) << name << " differs between the command and the library (fast solver)";
  }
  EXPECT_THAT(fa.at("run.json"), HasSubstr("\"solver\": \"fast (tables, raw mosaic)\""));
  EXPECT_THAT(fa.at("run.json"), HasSubstr("\"geometry\": \"none\""));
  EXPECT_THAT(a.at("run.json"), HasSubstr("\"geometry\": \"ground_truth\""));
  EXPECT_THAT(a.at("run.json"), HasSubstr("\"solver\": \"per pixel\""));
  EXPECT_THAT(a.at("run.json"), HasSubstr("\"cameras_placed_by\": \"simulator truth\""));
  EXPECT_THAT(fa.at("run.json"), HasSubstr("\"cameras_placed_by\": \"the rig's nominal models (uncalibrated)\""));

  // A cancelled job stops before its next camera frame and says so; nothing more is written.
  processing::PhotometricJob cancelled_job = fast_job;
  cancelled_job.output_dir = dir + "/derived/cancelled";
  int asked = 0;
  auto cancelled = processing::RunPhotometric(cancelled_job, {}, [&] { return ++asked > 1; });
  EXPECT_EQ(cancelled.status().code(), absl::StatusCode::kCancelled) << cancelled.status();
  EXPECT_THAT(std::string(cancelled.status().message()), HasSubstr("cancelled after 1 of 3 camera frame(s)"));
  EXPECT_TRUE(fs::exists(dir + "/derived/cancelled/frame-000000/hs-1/metrics.json"));
  EXPECT_FALSE(fs::exists(dir + "/derived/cancelled/frame-000000/hs-2"));
  EXPECT_FALSE(fs::exists(dir + "/derived/cancelled/run.json"));

  // The evaluation against the take's ground truth.
  CommandResult eval =
      RunCommand({"stage-process", "evaluate", "photometric", "--take", dir, "--json"}, std::chrono::seconds(120));
  ASSERT_EQ(eval.exit.exit_code, 0) << eval.err;
  const nlohmann::json table = nlohmann::json::parse(eval.out);
  EXPECT_EQ(table["units"], 3);
  ASSERT_EQ(table["maps"].size(), 5u);
  EXPECT_EQ(table["maps"][0]["map"], "diffuse normal");
  EXPECT_GT(table["maps"][0]["pixels"].get<int64_t>(), 1000);
  EXPECT_GT(table["maps"][0]["mean"].get<double>(), 0);
  EXPECT_LT(table["maps"][0]["mean"].get<double>(), 10);
  CommandResult text = RunCommand({"stage-process", "evaluate", "photometric", "--take", dir, "--cameras", "hs-2"},
                                  std::chrono::seconds(120));
  EXPECT_THAT(text.out, HasSubstr("1 camera frame(s)"));
  EXPECT_THAT(text.out, HasSubstr("pore band"));

  // Bad requests say what is wrong and write nothing.
  CommandResult unknown =
      RunCommand({"stagectl", "--endpoints", endpoints, "process", "nope"}, std::chrono::seconds(30));
  EXPECT_EQ(unknown.exit.exit_code, 2);
  EXPECT_THAT(unknown.err, HasSubstr("no take \"nope\""));
  CommandResult stage_name =
      RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage", "uv-maps"}, std::chrono::seconds(30));
  EXPECT_EQ(stage_name.exit.exit_code, 2);
  EXPECT_THAT(
      stage_name.err,
      HasSubstr("--stage: \"uv-maps\" is not a stage (graph, photometric, calibration, mvs, fit, textures, stabilize, "
                "asset-dataset, asset-train, asset-infer)"));
  CommandResult no_take =
      RunCommand({"stage-process", "photometric", "--take", root.path() + "/missing"}, std::chrono::seconds(30));
  EXPECT_EQ(no_take.exit.exit_code, 2);
  EXPECT_THAT(no_take.err, HasSubstr(root.path() + "/missing/take.json"));
  CommandResult past =
      RunCommand({"stage-process", "photometric", "--take", dir, "--frames", "4", "--output", dir + "/derived/past"},
                 std::chrono::seconds(60));
  EXPECT_EQ(past.exit.exit_code, 2);
  EXPECT_THAT(past.err, HasSubstr("frames [4, 5) are not all in the take (it holds 1 whole frame(s))"));
  EXPECT_FALSE(fs::exists(dir + "/derived/past/run.json"));
  CommandResult camera =
      RunCommand({"stage-process", "photometric", "--take", dir, "--cameras", "hs-9"}, std::chrono::seconds(60));
  EXPECT_EQ(camera.exit.exit_code, 2);
  EXPECT_THAT(camera.err, HasSubstr("no frame file for camera \"hs-9\""));
  CommandResult range =
      RunCommand({"stage-process", "photometric", "--take", dir, "--frames", "3:1"}, std::chrono::seconds(30));
  EXPECT_EQ(range.exit.exit_code, 2);
  EXPECT_THAT(range.err, HasSubstr("--frames \"3:1\" is not a frame range"));
  // Multi-view stereo's meshes are the default geometry: a take without them is refused, saying what to run, by the
  // command and by the worker alike.
  CommandResult no_mvs = RunCommand(
      {"stage-process", "photometric", "--take", dir, "--output", dir + "/derived/no-mvs"}, std::chrono::seconds(60));
  EXPECT_EQ(no_mvs.exit.exit_code, 2);
  EXPECT_THAT(no_mvs.err, HasSubstr(dir + "/derived/mvs: no multi-view stereo meshes (the default geometry): run the "
                                          "mvs stage first"));
  EXPECT_FALSE(fs::exists(dir + "/derived/no-mvs/run.json"));
  CommandResult no_mvs_worker = RunCommand(
      {"stagectl", "--endpoints", endpoints, "process", id, "--stage", "photometric", "--calibration", "ground_truth"},
      std::chrono::seconds(60));
  EXPECT_NE(no_mvs_worker.exit.exit_code, 0);
  EXPECT_THAT(no_mvs_worker.err, HasSubstr("or take --geometry none"));

  // The asset's stages by their names, their options carried through the controller to the worker, which refuses an
  // option of another network, any with inference, and a training without a dataset, saying so.
  CommandResult other_network = RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage",
                                            "asset-train", "--network", "expression", "--region-weight", "5"},
                                           std::chrono::seconds(60));
  EXPECT_NE(other_network.exit.exit_code, 0);
  EXPECT_THAT(other_network.err, HasSubstr("an option given is not one of the ASSET_NETWORK_EXPRESSION network's"));
  CommandResult infer_options = RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage",
                                            "asset-infer", "--cameras", "mv-13", "--iterations", "5"},
                                           std::chrono::seconds(60));
  EXPECT_NE(infer_options.exit.exit_code, 0);
  EXPECT_THAT(infer_options.err,
              HasSubstr(": worker \"worker-1\": PROCESSING_STAGE_ASSET_INFER takes no asset options"));
  EXPECT_THAT(infer_options.err, Not(HasSubstr("worker \"worker-1\": worker")));  // named once
  // The dataset's options and the training's reach the worker, which refuses them on the other's stage.
  CommandResult crop_in_training =
      RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage", "asset-train", "--crop-mm", "250"},
                 std::chrono::seconds(60));
  EXPECT_NE(crop_in_training.exit.exit_code, 0);
  EXPECT_THAT(crop_in_training.err, HasSubstr("the asset's training takes no frames, cameras, calibration"));
  CommandResult rate_in_dataset = RunCommand(
      {"stagectl", "--endpoints", endpoints, "process", id, "--stage", "asset-dataset", "--learning-rate", "0.001"},
      std::chrono::seconds(60));
  EXPECT_NE(rate_in_dataset.exit.exit_code, 0);
  EXPECT_THAT(rate_in_dataset.err, HasSubstr("the asset's dataset takes no training options"));
  CommandResult no_dataset = RunCommand({"stagectl", "--endpoints", endpoints, "process", id, "--stage", "asset-train",
                                         "--network", "geometry", "--region-weight", "5", "--iterations", "2"},
                                        std::chrono::seconds(60));
  EXPECT_NE(no_dataset.exit.exit_code, 0);
  EXPECT_THAT(no_dataset.err, HasSubstr(dir + "/derived/asset/dataset.h5"));
}

}  // namespace
}  // namespace stage::testing
