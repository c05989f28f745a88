// stage-process: runs processing stages on a take from the command line (the batch form; the same library call the
// ProcessingWorker service makes), and evaluates their results against the simulator's ground truth.
#include <iostream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_split.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/version.h"
#include "stage/processing/evaluate.h"
#include "stage/processing/photometric_stage.h"

namespace {

constexpr const char* kProgram = "stage-process";

std::vector<std::string> SplitCameras(const std::string& list) {
  std::vector<std::string> out;
  for (absl::string_view id : absl::StrSplit(list, ',', absl::SkipEmpty())) out.emplace_back(id);
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Runs FaStage processing stages on a take (the batch form of the ProcessingWorker service), and "
               "evaluates their results against the simulator's ground truth.",
               kProgram};
  app.set_version_flag("--version", std::string(kProgram) + " (FaStage) " + std::string(stage::kVersion));
  app.require_subcommand(1);
  std::string log_level;
  app.add_option("--log-level", log_level, "Log levels, e.g. debug (overrides SPDLOG_LEVEL)");

  stage::processing::PhotometricJob job;
  std::string frames = "0:", cameras, threads_help;
  bool json = false;
  CLI::App* photometric = app.add_subcommand(
      "photometric",
      "Photometric stereo: per frame and high-speed camera, diffuse and specular normals, albedo, specular intensity, "
      "roughness and confidence, into TAKE/derived/photometric/frame-NNNNNN/CAMERA/ (OpenEXR, PNG previews, "
      "metrics.json, contact_sheet.png)");
  photometric->add_option("--take", job.take_dir, "The take directory (takes/<take-id>)")->required();
  photometric->add_option("--frames", frames, "Virtual frames A:B (B excluded), A: to the end, or A")
      ->capture_default_str();
  photometric->add_option("--cameras", cameras, "Camera ids, comma-separated (default: every high-speed camera)");
  photometric->add_option(
      "--geometry", job.geometry,
      "Surface geometry: a directory with frame-NNNNNN/mesh.obj per frame, relative to the take or absolute (e.g. "
      "ground_truth on a simulated take, until multi-view stereo gives it); default: none");
  photometric->add_option(
      "--calibration", job.calibration,
      "Where the cameras are: a calibration file or a directory holding cameras.json (stage-process calibrate's "
      "output; ground_truth on a simulated take), relative to the take or absolute; default: the rig's nominal models");
  photometric->add_option("--output", job.output_dir, "Results directory (default: TAKE/derived/photometric)");
  photometric->add_option("--threads", job.options.threads, "Worker threads (default 0: one per core)")
      ->check(CLI::NonNegativeNumber);
  photometric->add_option("--specular-filter-radius", job.options.specular_filter_radius,
                          "Radius (pixels) of the adaptive filter on specular normals and roughness; 0: raw fits")
      ->capture_default_str()
      ->check(CLI::Range(0, 16));
  photometric->add_flag("--exact", job.exact,
                        "Without --geometry too, fit the specular lobe per pixel instead of the table-driven solver "
                        "(slower, less noisy specular maps)");
  photometric->add_flag("--json", json, "Print the result as JSON on stdout");

  stage::processing::EvaluateOptions eval;
  std::string eval_frames = "0:", eval_cameras;
  bool eval_json = false;
  CLI::App* evaluate = app.add_subcommand("evaluate", "Compare a stage's results with the take's ground truth");
  evaluate->require_subcommand(1);
  CLI::App* eval_photometric = evaluate->add_subcommand(
      "photometric",
      "Per map: mean and median error on the subject mask (normals: angle; albedo and specular: relative; "
      "roughness: absolute), and the same in the pore band (detail finer than --band-sigma pixels) beside the "
      "truth's own detail there");
  eval_photometric->add_option("--take", eval.take_dir, "The take directory")->required();
  eval_photometric->add_option("--frames", eval_frames, "Virtual frames A:B, A: or A")->capture_default_str();
  eval_photometric->add_option("--cameras", eval_cameras, "Camera ids, comma-separated (default: all with results)");
  eval_photometric->add_option("--results", eval.results_dir, "Results (default: TAKE/derived/photometric)");
  eval_photometric->add_option("--truth", eval.truth_dir, "Ground truth (default: TAKE/ground_truth)");
  eval_photometric->add_option("--band-sigma", eval.band_sigma_px, "The pore band: detail finer than this, pixels")
      ->capture_default_str()
      ->check(CLI::Range(0.5, 50.0));
  eval_photometric->add_flag("--json", eval_json, "Print the table as JSON on stdout");

  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  if (auto s = stage::InitLogging(kProgram, log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  if (*photometric) {
    if (auto s = stage::ParseFrameRange("--frames", frames, &job.first_frame, &job.last_frame); !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    job.cameras = SplitCameras(cameras);
    stage::ProgressLine bar("camera frames");
    auto result = stage::processing::RunPhotometric(job, [&](const stage::processing::JobProgress& p) {
      if (p.done == 0) {
        bar.Message(p.message);
      } else {
        bar.Update(p.done, p.total, p.message);
      }
    });
    bar.Finish();
    if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
    if (json) {
      std::cout << nlohmann::json{{"output_dir", result->output_dir}, {"units", result->units}}.dump() << "\n";
    } else {
      std::cout << result->units << " camera frame(s) processed into " << result->output_dir << "\n";
    }
    return 0;
  }
  if (*eval_photometric) {
    if (auto s = stage::ParseFrameRange("--frames", eval_frames, &eval.first_frame, &eval.last_frame); !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    eval.cameras = SplitCameras(eval_cameras);
    auto result = stage::processing::EvaluatePhotometric(eval);
    if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
    std::cout << (eval_json ? stage::processing::EvaluationJson(*result) + "\n"
                            : stage::processing::FormatEvaluation(*result));
    return 0;
  }
  return 0;
}
