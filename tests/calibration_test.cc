// Camera calibration on the simulated stage, the three ways a user runs it: `stagectl calibrate` (a take of the board
// recorded and calibrated on the stage's worker), the batch command (stage-process calibrate) and the library call,
// which write the same calibration; it finds the simulator's seeded camera deviations (bounds for the reduced render
// scale), a camera whose nominal pose is 10 mm wrong, and names the cameras that never saw the board.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/file_util.h"
#include "stage/processing/calibrate.h"
#include "test_support.h"

namespace stage::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

std::string Slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream bytes;
  bytes << in.rdbuf();
  return bytes.str();
}

using CalibrationTest = SimulatedStageTest;

TEST_F(CalibrationTest, TheStageCalibratesItsCamerasFromATakeOfTheBoard) {
  TempDir root;
  // 2 s of the board performance turn it towards every camera (render scale 0.125: 324 x 256 machine-vision images).
  ASSERT_NO_FATAL_FAILURE(
      StartStage({"--set", "sim.subject.kind=charuco", "--set", "sim.render_scale=0.125", "--take-root", root.path()}));
  CommandResult cal = RunCommand({"stagectl", "--endpoints", Endpoints(), "calibrate", "--seconds", "2", "--json"},
                                 std::chrono::seconds(2400));
  // About 10 minutes on 2 cores (the board drawn without shadow rays; the take's ground truth only its scene: the true
  // cameras and the board's poses), twice that with both cores busy. Shorter takes do not hold these bounds: the same
  // poses at twice the speed (24 frames, 5 minutes) gave centres 1.15 mm RMS and rotations 0.141 deg, at 4/3 of it (36
  // frames) 1.59 mm and 0.121 deg (a camera's distance traded against its focal length).
  ASSERT_FALSE(cal.timed_out) << cal.err;
  ASSERT_EQ(cal.exit.exit_code, 0) << cal.err;
  const nlohmann::json done = nlohmann::json::parse(cal.out);
  const std::string out = done["output_dir"];
  const std::string dir = fs::path(out).parent_path().parent_path().string();
  EXPECT_EQ(out, dir + "/derived/calibration");
  EXPECT_THAT(std::string(done["message"]), HasSubstr("27 camera(s) from 48 frame(s)"));
  EXPECT_THAT(cal.err, HasSubstr("28/28 cameras"));
  // The truth of a calibration take: the true cameras and each frame's board, no per-camera maps.
  EXPECT_TRUE(fs::exists(dir + "/ground_truth/cameras.json"));
  EXPECT_TRUE(fs::exists(dir + "/ground_truth/frame-000047/pose.json"));
  EXPECT_FALSE(fs::exists(dir + "/ground_truth/frame-000000/mv-01"));

  // The batch command and the library write the same calibration.
  CommandResult batch =
      RunCommand({"stage-process", "calibrate", "--take", dir, "--output", dir + "/derived/batch", "--json"},
                 std::chrono::seconds(300));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  processing::CalibrationJob job;
  job.take_dir = dir;
  job.output_dir = dir + "/derived/library";
  auto library = processing::RunCalibration(job);
  ASSERT_TRUE(library.ok()) << library.status();
  const std::string worker_bytes = Slurp(out + "/cameras.json");
  EXPECT_TRUE(worker_bytes == Slurp(dir + "/derived/batch/cameras.json")) << "the worker's and the batch's differ";
  EXPECT_TRUE(worker_bytes == Slurp(dir + "/derived/library/cameras.json")) << "the worker's and the library's differ";
  // The reports differ only in where they say the calibration went.
  auto report_of = [&](const std::string& where) {
    nlohmann::json r = nlohmann::json::parse(Slurp(where + "/report.json"));
    EXPECT_EQ(r["output"], where + "/cameras.json");
    r.erase("output");
    return r.dump();
  };
  const std::string worker_report = report_of(out);
  EXPECT_TRUE(worker_report == report_of(dir + "/derived/batch")) << "the worker's and the batch's reports differ";
  EXPECT_TRUE(worker_report == report_of(dir + "/derived/library")) << "the worker's and the library's reports differ";

  // Against the truth. Bounds for render scale 0.125, where the corners are found to ~0.1 px (0.8 sensor pixels; 0.023
  // px at 0.25). Measured: reprojection RMS 0.092 px; where the cameras see the head's volume (projection) RMS 0.19 and
  // worst 0.49 sensor pixels against the nominal models' 39.4 and 94.1; centres RMS 0.62 mm (nominal 2.4), rotations
  // 0.087 deg (0.29), focal lengths 0.06 % (0.49 %). (Before sheared squares' corners were dropped: 0.146 px, 0.33 and
  // 0.95, 1.5 mm, 0.11 deg.) The centres' error runs along each camera's axis with its focal length's (a board 1 m
  // away fixes f / distance much better than either): the figures at 0.25 and the full-scale goals are in
  // docs/geometry.md.
  ASSERT_TRUE(library->has_truth);
  const processing::TruthComparison& t = library->truth;
  std::printf(
      "calibration against the truth: reprojection RMS %.3f px; projection RMS %.2f worst %.2f sensor px (nominal "
      "%.1f); centres RMS %.2f mm, rotations RMS %.3f deg (nominal %.3f)\n",
      library->rms_px, t.rms.projection_px, t.worst.projection_px, library->nominal_truth.rms.projection_px,
      t.rms.centre_mm, t.rms.rotation_deg, library->nominal_truth.rms.rotation_deg);
  EXPECT_EQ(t.cameras.size(), 27u);
  EXPECT_LT(library->rms_px, 0.15);
  EXPECT_LT(t.rms.projection_px, 0.35);
  EXPECT_LT(t.worst.projection_px, 1.0);
  EXPECT_LT(t.rms.projection_px, library->nominal_truth.rms.projection_px / 100);
  EXPECT_LT(t.rms.centre_mm, 1.2);
  EXPECT_LT(t.rms.rotation_deg, 0.15);
  EXPECT_LT(t.rms.rotation_deg, library->nominal_truth.rms.rotation_deg / 2);
  CommandResult eval =
      RunCommand({"stage-process", "evaluate", "calibration", "--take", dir, "--json"}, std::chrono::seconds(60));
  ASSERT_EQ(eval.exit.exit_code, 0) << eval.err;
  EXPECT_EQ(nlohmann::json::parse(eval.out)["calibrated"]["cameras"].size(), 27u);

  // A camera whose nominal pose is 10 mm off: found where it is all the same.
  const std::string take_json = Slurp(dir + "/take.json");
  nlohmann::json take = nlohmann::json::parse(take_json);
  for (auto& c : take["rig"]["cameras"]) {
    if (c["id"] == "mv-05") c["pose"]["position_mm"]["x"] = c["pose"]["position_mm"]["x"].get<double>() + 10;
  }
  ASSERT_TRUE(WriteFileAtomically(dir + "/take.json", take.dump()).ok());
  job.output_dir = dir + "/derived/wrong-nominal";
  auto wrong = processing::RunCalibration(job);
  ASSERT_TRUE(WriteFileAtomically(dir + "/take.json", take_json).ok());
  ASSERT_TRUE(wrong.ok()) << wrong.status();
  EXPECT_LT(wrong->rms_px, 0.25);
  for (size_t i = 0; i < t.cameras.size(); ++i) {
    if (t.cameras[i].id != "mv-05") continue;
    // Where it was found with the right nominal pose, within half a pixel, though its nominal centre is now ~10 mm
    // off.
    EXPECT_NEAR(wrong->truth.cameras[i].projection_px, t.cameras[i].projection_px, 0.5);
    EXPECT_GT(wrong->nominal_truth.cameras[i].centre_mm, 7);
  }

  // Cameras that never see the board are named, and the others' calibration is still written.
  job.output_dir = dir + "/derived/front-only";
  job.options.last_frame = 4;  // the board square to the front cameras
  auto front = processing::RunCalibration(job);
  ASSERT_FALSE(front.ok());
  EXPECT_THAT(std::string(front.status().message()), HasSubstr("mv-01 (never saw the board in 4 full-lit frame(s))"));
  EXPECT_TRUE(fs::exists(dir + "/derived/front-only/cameras.json"));
  const nlohmann::json report = nlohmann::json::parse(Slurp(dir + "/derived/front-only/report.json"));
  EXPECT_GE(report["missing"].size(), 4u);
}

}  // namespace
}  // namespace stage::testing
