// stage-process: runs processing stages on a take from the command line (the batch form; the same library call the
// ProcessingWorker service makes), and evaluates their results against the simulator's ground truth.
#include <functional>
#include <iostream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_split.h"
#include "asset_commands.h"
#include "graph_commands.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/version.h"
#include "stage/processing/calibrate.h"
#include "stage/processing/evaluate.h"
#include "stage/processing/evaluate_assets.h"
#include "stage/processing/evaluate_mvs.h"
#include "stage/processing/mvs.h"
#include "stage/processing/photometric_stage.h"
#include "stage/processing/stabilize.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/texture_fusion.h"

namespace {

constexpr const char* kProgram = "stage-process";

std::vector<std::string> SplitCameras(const std::string& list) {
  std::vector<std::string> out;
  for (absl::string_view id : absl::StrSplit(list, ',', absl::SkipEmpty())) out.emplace_back(id);
  return out;
}

// A job's progress on `bar`: its first message (nothing done yet) as a line, then the bar.
std::function<void(const stage::processing::JobProgress&)> ShowOn(stage::ProgressLine& bar) {
  return [&bar](const stage::processing::JobProgress& p) {
    if (p.done == 0) {
      bar.Message(p.message);
    } else {
      bar.Update(p.done, p.total, p.message);
    }
  };
}

// A stage over frames run from the command line: --frames, a progress bar, and the result as JSON or in words
// ("N frame(s) VERB into DIR").
template <typename Job, typename RunJob>
int RunOverFrames(const std::string& frames, bool json, const char* verb, Job* job, RunJob run) {
  if (auto s = stage::ParseFrameRange("--frames", frames, &job->first_frame, &job->last_frame); !s.ok()) {
    return stage::ReportFatal(kProgram, s);
  }
  stage::ProgressLine bar("frames");
  auto result = run(*job, ShowOn(bar), {});
  bar.Finish();
  if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
  if (json) {
    std::cout << nlohmann::json{{"output_dir", result->output_dir}, {"frames", result->units}}.dump() << "\n";
  } else {
    std::cout << result->units << " frame(s) " << verb << " into " << result->output_dir << "\n";
  }
  return 0;
}

// `stage-process mvs`: its options, and the run.
struct MvsCommand {
  stage::processing::MvsJob job;
  std::string frames = "0:", cameras;
  bool json = false;
  CLI::App* app = nullptr;

  void Add(CLI::App& parent) {
    app = parent.add_subcommand(
        "mvs",
        "Multi-view stereo: per frame, a depth map per machine-vision camera from its full-lit image and its "
        "neighbours', filtered by agreement, fused (TSDF) and meshed: TAKE/derived/mvs/frame-NNNNNN/mesh.obj (stage "
        "frame, mm), depth/CAMERA.exr, metrics.json");
    stage::processing::MvsOptions& o = job.options;
    app->add_option("--take", job.take_dir, "The take directory (takes/<take-id>)")->required();
    app->add_option("--frames", frames, "Virtual frames A:B (B excluded), A: to the end, or A")->capture_default_str();
    app->add_option("--cameras", cameras, "Camera ids, comma-separated (default: every machine-vision camera)");
    app->add_option("--calibration", job.calibration,
                    "Where the cameras are: a calibration file or a directory holding cameras.json, relative to the "
                    "take or absolute; default: the rig's nominal models");
    app->add_option("--output", job.output_dir, "Results directory (default: TAKE/derived/mvs)");
    app->add_option("--image-scale", o.image_scale, "Processing resolution relative to the recorded images")
        ->capture_default_str()
        ->check(CLI::Range(0.05, 1.0));
    app->add_option("--neighbours", o.neighbours, "Views each view is matched against")
        ->capture_default_str()
        ->check(CLI::Range(1, 16));
    app->add_option("--window", o.window, "Correlation window, pixels (odd)")->capture_default_str();
    app->add_option("--min-score", o.min_score, "Correlation a depth must reach")->capture_default_str();
    app->add_option("--fine-min-score", o.fine_min_score,
                    "... where a pixel covers less than --fine-footprint-mm at the head")
        ->capture_default_str();
    app->add_option("--fine-footprint-mm", o.fine_footprint_mm,
                    "Pixel footprint below which --fine-min-score applies, mm (0: never)")
        ->capture_default_str()
        ->check(CLI::NonNegativeNumber);
    app->add_option("--prior-median", o.prior_median_radius,
                    "Median filter of each coarser level's depth before the finer level sweeps about it, radius in "
                    "coarser pixels (0: none)")
        ->capture_default_str()
        ->check(CLI::Range(0, 8));
    app->add_flag("--keep-coarser,!--no-keep-coarser", o.keep_coarser,
                  "Where a finer level finds no depth, keep the coarser level's (fewer holes, more noise)");
    app->add_option("--min-views", o.min_views, "Views a surface needs to be meshed")
        ->capture_default_str()
        ->check(CLI::Range(1, 64));
    app->add_option("--truncation-voxels", o.truncation_voxels, "Truncation of the signed distance, voxels")
        ->capture_default_str();
    app->add_option("--voxel-mm", o.voxel_mm, "Voxel of the fused volume, mm (0: a pixel's footprint)")
        ->capture_default_str();
    app->add_option("--volume-radius-mm", o.volume_radius_mm, "Radius of the head's volume about the stage origin")
        ->capture_default_str();
    app->add_option("--silhouette-grow-px", o.silhouette_grow_px,
                    "Grow each view's silhouette (the visual hull's evidence, written beside the mesh) by this many "
                    "pixels")
        ->capture_default_str()
        ->check(CLI::Range(0, 16));
    app->add_option("--fill-holes-mm", o.fill_holes_mm, "Close the mesh's holes at most this wide, mm (0: none)")
        ->capture_default_str()
        ->check(CLI::NonNegativeNumber);
    app->add_option("--smooth", o.smooth_iterations, "Taubin smoothing of the mesh, iterations")
        ->capture_default_str()
        ->check(CLI::Range(0, 1000));
    app->add_option("--threads", o.threads, "Worker threads (default 0: one per core)")->check(CLI::NonNegativeNumber);
    app->add_flag("--json", json, "Print the result as JSON on stdout");
  }

  int Run() {
    job.cameras = SplitCameras(cameras);
    return RunOverFrames(frames, json, "reconstructed", &job, stage::processing::RunMvs);
  }
};

// `stage-process fit`: its options, and the run.
struct FitCommand {
  stage::processing::FitJob job;
  std::string frames = "0:", surface = "mvs", nonrigid = "auto";
  bool json = false;
  CLI::App* app = nullptr;

  void Add(CLI::App& parent) {
    app = parent.add_subcommand(
        "fit",
        "The face template fitted to every frame's surface, tracked through the take (docs/assets.md): "
        "TAKE/derived/fit/frame-NNNNNN/mesh.obj (the template's topology and UVs, stage frame, mm), "
        "geometry_map.exr (head frame), pose.json, metrics.json");
    app->add_option("--take", job.take_dir, "The take directory (takes/<take-id>)")->required();
    app->add_option("--frames", frames, "Virtual frames A:B (B excluded), A: to the last surface, or A")
        ->capture_default_str();
    app->add_option("--surface", surface,
                    "The surfaces: mvs (multi-view stereo's meshes, TAKE/derived/mvs) or a directory of "
                    "frame-NNNNNN/mesh.obj relative to the take or absolute (ground_truth on a simulated take)")
        ->capture_default_str();
    app->add_option("--template", job.template_obj,
                    "The face template, FILE.obj with FILE.json beside it (default: the shipped one)");
    app->add_option("--output", job.output_dir, "Results directory (default: TAKE/derived/fit)");
    app->add_option("--map-size", job.map.size, "Texels across the geometry map")
        ->capture_default_str()
        ->check(CLI::Range(16, 8192));
    app->add_option("--map-dilation", job.map.dilation_px, "Rings of texels grown past the layout's edges")
        ->capture_default_str()
        ->check(CLI::Range(0, 64));
    app->add_option("--max-distance-mm", job.options.max_distance_mm,
                    "Correspondences further than this from the surface are left out, mm")
        ->capture_default_str()
        ->check(CLI::PositiveNumber);
    app->add_option("--stiffness", job.options.stiffness,
                    "The non-rigid stages' membrane stiffness, stiff to supple (a weight against each vertex's data "
                    "term of 1)")
        ->capture_default_str()
        ->delimiter(',');
    app->add_flag("!--keep-border", job.options.skip_border,
                  "Keep correspondences on the surface's border (holes' rims), which the fit leaves out by default");
    app->add_option("--nonrigid", nonrigid,
                    "How the non-rigid stages may move a vertex: auto (along the normal when the template's model "
                    "is fitted, else free), free, along_normal")
        ->capture_default_str()
        ->check(CLI::IsMember({"auto", "free", "along_normal"}));
    app->add_option("--model-iterations", job.options.model_iterations,
                    "Gauss-Newton iterations of the template's shape and expression model between placement and "
                    "non-rigid ICP; 0: the template's own shape")
        ->capture_default_str()
        ->check(CLI::Range(0, 1000));
    app->add_option("--identity-prior", job.options.identity_prior,
                    "Weight holding each identity coefficient toward the template: a standard deviation costs as "
                    "much as this many vertices off by the fit's typical residual")
        ->capture_default_str()
        ->check(CLI::NonNegativeNumber);
    app->add_option("--expression-prior", job.options.expression_prior,
                    "Weight holding each expression coefficient toward neutral: a whole blendshape costs as much as "
                    "this many vertices off by the fit's typical residual")
        ->capture_default_str()
        ->check(CLI::NonNegativeNumber);
    app->add_option("--identity-reach", job.options.identity_reach,
                    "The identity's coefficients are kept within this many standard deviations")
        ->capture_default_str()
        ->check(CLI::PositiveNumber);
    app->add_flag("--json", json, "Print the result as JSON on stdout");
  }

  int Run() {
    job.surface = stage::processing::GeometrySpec::Parse(surface);
    job.options.nonrigid = *stage::processing::ParseNonRigidMotion(nonrigid);  // CLI11 checked the word
    return RunOverFrames(frames, json, "fitted", &job, stage::processing::RunFit);
  }
};

// `stage-process textures`: its options, and the run.
struct TexturesCommand {
  stage::processing::TexturesJob job;
  std::string frames = "0:", cameras;
  bool json = false;
  CLI::App* app = nullptr;

  void Add(CLI::App& parent) {
    app = parent.add_subcommand(
        "textures",
        "The views' photometric maps fused into the fitted template's UV layout (docs/assets.md): "
        "TAKE/derived/textures/frame-NNNNNN/ albedo, specular, roughness, normal_object (head frame) and "
        "normal_tangent as OpenEXR with PNG previews, a contact sheet, metrics.json");
    app->add_option("--take", job.take_dir, "The take directory (takes/<take-id>)")->required();
    app->add_option("--frames", frames, "Virtual frames A:B (B excluded), A: to the last fitted frame, or A")
        ->capture_default_str();
    app->add_option("--cameras", cameras,
                    "Comma-separated views (default: every camera with photometric maps in the first frame)");
    app->add_option("--calibration", job.calibration,
                    "Where the cameras are: a calibration file or a directory holding cameras.json, relative to the "
                    "take or absolute (default: the rig's nominal models)");
    app->add_option("--fit", job.fit_dir, "The fitted template (default: TAKE/derived/fit)");
    app->add_option("--photometric", job.photometric_dir, "The photometric maps (default: TAKE/derived/photometric)");
    app->add_option("--output", job.output_dir, "Results directory (default: TAKE/derived/textures)");
    app->add_option("--size", job.options.size, "Texels across the textures")
        ->capture_default_str()
        ->check(CLI::Range(16, 16384));
    app->add_option("--max-view-angle-deg", job.options.max_view_angle_deg,
                    "Views seeing the surface more obliquely weigh nothing, degrees")
        ->capture_default_str()
        ->check(CLI::Range(1.0, 89.0));
    app->add_option("--max-lobe-view-angle-deg", job.options.max_lobe_view_angle_deg,
                    "A view's specular lobe is fused only where it sees the surface within this angle of its normal "
                    "(more obliquely, the solve's specular normal tilts towards the camera), degrees")
        ->capture_default_str()
        ->check(CLI::Range(1.0, 89.0));
    app->add_option("--feather-px", job.options.feather_px,
                    "A view's weight rises to full over this many of its pixels from the edge of what it sees")
        ->capture_default_str()
        ->check(CLI::Range(0.0, 256.0));
    app->add_option("--dilation", job.options.dilation_px, "Rings of texels grown past the covered ones")
        ->capture_default_str()
        ->check(CLI::Range(0, 64));
    app->add_flag("--json", json, "Print the result as JSON on stdout");
  }

  int Run() {
    job.cameras = SplitCameras(cameras);
    return RunOverFrames(frames, json, "of textures fused", &job, stage::processing::RunTextures);
  }
};

struct StabilizeCommand {
  stage::processing::StabilizeJob job;
  std::string frames = "0:", method = "flow";
  bool json = false, net_alone = false;
  CLI::App* app = nullptr;

  void Add(CLI::App& parent) {
    app = parent.add_subcommand(
        "stabilize",
        "The fused textures of every frame warped onto the first frame's along a warp found on the albedos in UV, "
        "by optical flow or by a self-supervised U-Net trained on the take's frames "
        "(docs/assets.md#temporal-stabilization): TAKE/derived/textures-stable/frame-NNNNNN/, the same files, "
        "wrinkle.exr (U-Net), metrics.json with the flow and the albedo's jitter to the frame before");
    app->add_option("--take", job.take_dir, "The take directory (takes/<take-id>)")->required();
    app->add_option("--frames", frames,
                    "Virtual frames A:B (B excluded), A: to the last frame with textures, or A; the first is the "
                    "reference")
        ->capture_default_str();
    app->add_option("--textures", job.textures_dir, "The fused textures (default: TAKE/derived/textures)");
    app->add_option("--output", job.output_dir, "Results directory (default: TAKE/derived/textures-stable)");
    app->add_option("--patch-size", job.options.patch_size, "The optical flow's patches, texels")
        ->capture_default_str()
        ->check(CLI::Range(4, 64));
    app->add_option("--max-flow", job.options.max_flow_px, "A longer flow is not trusted, texels")
        ->capture_default_str();
    app->add_option("--method", method, "flow (OpenCV's DIS, frame by frame) or unet (trained on the frames)")
        ->capture_default_str()
        ->check(CLI::IsMember({"flow", "unet"}));
    stage::processing::WarpNetOptions& net = job.options.net;
    app->add_option("--net-size", job.options.net_size, "The U-Net's resolution, texels across (a power of two)")
        ->capture_default_str();
    app->add_option("--net-levels", net.levels, "The U-Net's levels")->capture_default_str();
    app->add_option("--net-channels", net.base_channels, "The U-Net's channels at its first level")
        ->capture_default_str();
    app->add_option("--iterations", net.iterations, "The U-Net's training steps")->capture_default_str();
    app->add_option("--learning-rate", net.learning_rate, "Adam's learning rate")->capture_default_str();
    app->add_option("--smoothness", net.smoothness, "Weight of the warp's smoothness loss")->capture_default_str();
    app->add_option("--wrinkle-sparsity", net.wrinkle_sparsity, "Weight of the wrinkle map's L1 loss")
        ->capture_default_str();
    app->add_option("--wrinkle-smoothness", net.wrinkle_smoothness, "Weight of the wrinkle map's gradient loss")
        ->capture_default_str();
    app->add_flag("--net-alone", net_alone,
                  "The U-Net finds the whole warp (by default it corrects the optical flow's)");
    app->add_option("--threads", net.threads, "Torch's threads (0: the cores this process may run on)")
        ->capture_default_str();
    app->add_option("--seed", net.seed, "The U-Net's initialization and the frames' order")->capture_default_str();
    app->add_flag("--json", json, "Print the result as JSON on stdout");
  }

  int Run() {
    job.options.method = *stage::processing::ParseStabilizeMethod(method);  // CLI11 checked the word
    job.options.net_from_flow = !net_alone;
    // No option is ignored: the U-Net's belong to --method unet, the flow's patches to the flow (alone, or the
    // U-Net's base).
    const bool unet = job.options.method == stage::processing::StabilizeMethod::kUNet;
    for (const char* name :
         {"--net-alone", "--net-size", "--net-levels", "--net-channels", "--iterations", "--learning-rate",
          "--smoothness", "--wrinkle-sparsity", "--wrinkle-smoothness", "--threads", "--seed"}) {
      if (!unet && app->count(name) > 0) {
        return stage::ReportFatal(kProgram,
                                  absl::InvalidArgumentError(absl::StrCat(name, " applies to --method unet")));
      }
    }
    if (unet && net_alone && app->count("--patch-size") > 0) {
      return stage::ReportFatal(
          kProgram,
          absl::InvalidArgumentError("--patch-size applies to the optical flow, which --net-alone does not use"));
    }
    return RunOverFrames(frames, json, "stabilized", &job, stage::processing::RunStabilize);
  }
};

}  // namespace

// The command line's work, once the process is set up: also what a graph task calls for its stage, in process.
int Dispatch(int argc, char** argv) {
  CLI::App app{
      "Runs FaStage processing stages on a take (the batch form of the ProcessingWorker service), and "
      "evaluates their results against the simulator's ground truth.",
      kProgram};
  app.set_version_flag("--version", std::string(kProgram) + " (FaStage) " + std::string(stage::kVersion));
  app.require_subcommand(1);
  std::string log_level;
  app.add_option("--log-level", log_level, "Log levels, e.g. debug (overrides SPDLOG_LEVEL)");

  stage::processing::PhotometricJob job;
  std::string frames = "0:", cameras, threads_help, geometry = "mvs";
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
  photometric
      ->add_option(
          "--geometry", geometry,
          "Surface geometry: mvs (multi-view stereo's meshes, TAKE/derived/mvs: run stage-process mvs first), none "
          "(every pixel sees the units from the stage origin), or a directory with frame-NNNNNN/mesh.obj per frame, "
          "relative to the take or absolute (ground_truth on a simulated take: the truth's)")
      ->capture_default_str();
  photometric->add_option(
      "--calibration", job.calibration,
      "Where the cameras are: a calibration file or a directory holding cameras.json (stage-process calibrate's "
      "output; ground_truth on a simulated take), relative to the take or absolute; default: the rig's nominal models");
  photometric->add_option("--output", job.output_dir, "Results directory (default: TAKE/derived/photometric)");
  photometric->add_option("--threads", job.options.threads, "Worker threads (default 0: one per core)")
      ->check(CLI::NonNegativeNumber);
  photometric
      ->add_option("--specular-filter-radius", job.options.specular_filter_radius,
                   "Radius (pixels) of the adaptive filter on specular normals and roughness; 0: raw fits")
      ->capture_default_str()
      ->check(CLI::Range(0, 16));
  photometric
      ->add_option("--shadow-clearance-mm", job.options.shadow_clearance_mm,
                   "With geometry: shadow rays start this far from the surface, towards their light, mm (the "
                   "geometry's own roughness must not shadow it)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  photometric
      ->add_option("--geometry-fill-px", job.options.geometry_fill_px,
                   "With geometry: pixels the mesh misses within this many pixels of ones it covers (the sides of the "
                   "head a reconstruction does not reach) take their neighbours' distance; 0: none")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  photometric
      ->add_option("--geometry-refill-passes", job.options.geometry_refill_passes,
                   "With geometry: then the pixels so placed are placed again on the surface the solved normals "
                   "describe and solved again, this many times; 0: none")
      ->capture_default_str()
      ->check(CLI::Range(0, 4));
  photometric->add_flag("--geometry-hull,!--no-geometry-hull", job.options.geometry_hull,
                        "With geometry that has silhouettes (multi-view stereo's), keep the placed pixels' points "
                        "inside the frame's visual hull (default on)");
  photometric
      ->add_option(
          "--geometry-hull-depth-mm", job.options.geometry_hull_depth_mm,
          "With the visual hull: how far past where its ray enters the hull a placed pixel's point may lie, mm")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  photometric->add_flag("--exact", job.exact,
                        "With --geometry none too, fit the specular lobe per pixel instead of the table-driven "
                        "solver (slower, less noisy specular maps; with geometry it always does)");
  photometric->add_flag("--json", json, "Print the result as JSON on stdout");

  MvsCommand mvs;
  mvs.Add(app);
  FitCommand fit;
  fit.Add(app);
  TexturesCommand textures;
  textures.Add(app);
  StabilizeCommand stabilize;
  stabilize.Add(app);
  stage::process::AssetCommands asset;
  asset.Add(app);
  stage::process::GraphCommands graph;
  graph.Add(app);

  stage::processing::CalibrationJob cal;
  std::string cal_frames = "0:", cal_cameras;
  bool cal_json = false;
  CLI::App* calibrate = app.add_subcommand(
      "calibrate",
      "Camera calibration from a take of the ChArUco board: the board's corners in every camera's full-lit frames, "
      "one bundle adjustment over every camera and board pose, into TAKE/derived/calibration/cameras.json (what "
      "--calibration of the later stages reads) and report.json; against the truth too on a simulated take");
  calibrate->add_option("--take", cal.take_dir, "The calibration take's directory")->required();
  calibrate->add_option("--frames", cal_frames, "Virtual frames A:B, A: or A")->capture_default_str();
  calibrate->add_option("--cameras", cal_cameras, "Camera ids, comma-separated (default: every camera)");
  calibrate->add_option("--output", cal.output_dir, "Results directory (default: TAKE/derived/calibration)");
  calibrate->add_option("--min-corners", cal.options.min_corners, "Corners a view of the board needs")
      ->capture_default_str()
      ->check(CLI::Range(6, 10000));
  calibrate->add_option("--min-frames", cal.options.min_frames, "Frames with the board a camera needs")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  calibrate->add_option("--loss-px", cal.options.loss_px, "Huber loss scale, pixels of the recorded images")
      ->capture_default_str();
  calibrate->add_flag("--fit-k3", cal.options.fit_k3, "Fit the sixth-order radial term too");
  calibrate->add_flag("--require-all,!--no-require-all", cal.options.require_all,
                      "Fail when a camera cannot be calibrated (the default; --no-require-all lists it and goes on)");
  calibrate->add_flag("--json", cal_json, "Print the report as JSON on stdout");

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
  eval_photometric->add_option("--geometry-from", eval.geometry_from,
                               "Split the figures by the geometry each pixel was solved with, taken from this run's "
                               "results directory (default: the results' own, when solved with --geometry), so that "
                               "two runs are judged over the same pixels");
  eval_photometric
      ->add_option("--geometry-off", eval.geometry_off_mm,
                   "Split: a point on the mesh this far from the truth's surface (mm, camera z) or "
                   "farther counts as off it")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  eval_photometric->add_flag("--json", eval_json, "Print the table as JSON on stdout");

  std::string eval_cal_take, eval_cal_calibration;
  bool eval_cal_json = false;
  CLI::App* eval_calibration = evaluate->add_subcommand(
      "calibration",
      "Per camera: centre, rotation, focal length, principal point and distortion against the simulator's truth "
      "(TAKE/ground_truth/cameras.json), after the rigid motion that best fits the centres");
  eval_calibration->add_option("--take", eval_cal_take, "The take directory")->required();
  eval_calibration->add_option("--calibration", eval_cal_calibration,
                               "The calibration (default: TAKE/derived/calibration)");
  eval_calibration->add_flag("--json", eval_cal_json, "Print the table as JSON on stdout");

  stage::processing::MvsEvaluateOptions eval_mvs;
  std::string eval_mvs_frames = "0:";
  bool eval_mvs_json = false;
  CLI::App* eval_mvs_app = evaluate->add_subcommand(
      "mvs",
      "Per region of the head (skin, eyes, mouth): the distance of the reconstructed vertices to the true surface "
      "(RMSE, median, 95th percentile) and the share of the true surface two cameras see within --within-mm of the "
      "reconstruction");
  eval_mvs_app->add_option("--take", eval_mvs.take_dir, "The take directory")->required();
  eval_mvs_app->add_option("--frames", eval_mvs_frames, "Virtual frames A:B, A: or A")->capture_default_str();
  eval_mvs_app->add_option("--results", eval_mvs.results_dir, "Results (default: TAKE/derived/mvs)");
  eval_mvs_app->add_option("--truth", eval_mvs.truth_dir, "Ground truth (default: TAKE/ground_truth)");
  eval_mvs_app->add_option("--within-mm", eval_mvs.within_mm, "Completeness: true surface within this, mm")
      ->capture_default_str();
  eval_mvs_app
      ->add_option("--max-view-angle", eval_mvs.max_view_angle_deg,
                   "The true surface counts where 2 cameras see it at less than this from its normal, degrees")
      ->capture_default_str();
  std::string eval_mvs_pictures, eval_mvs_camera = "mv-05";
  eval_mvs_app->add_option("--pictures", eval_mvs_pictures,
                           "Also write PREFIX-mesh.png and PREFIX-error.png: the first frame's mesh as --camera sees "
                           "it, shaded, and its distance to the true surface (0-1 mm, colour map turbo)");
  eval_mvs_app->add_option("--camera", eval_mvs_camera, "The camera of --pictures")->capture_default_str();
  eval_mvs_app->add_flag("--json", eval_mvs_json, "Print the table as JSON on stdout");

  // evaluate fit / evaluate textures: one library call (EvaluateAssets), one of its two halves each.
  stage::processing::AssetsEvaluateOptions eval_assets;
  std::string eval_assets_frames = "0:";
  bool eval_assets_json = false;
  CLI::App* eval_fit = evaluate->add_subcommand(
      "fit",
      "Per frame and region (skin, eyes, mouth): every template vertex against where the head's layout puts its "
      "point on the true surface (RMSE, 99th percentile, distance to the surface, sliding along it)");
  CLI::App* eval_textures = evaluate->add_subcommand(
      "textures",
      "Per frame: the fused textures against the truth's per-camera maps fused through the same fit with the "
      "solve's weights (albedo relative, diffuse and specular normals in degrees), over all texels and those two or "
      "more views see");
  for (CLI::App* sub : {eval_fit, eval_textures}) {
    sub->add_option("--take", eval_assets.take_dir, "The take directory")->required();
    sub->add_option("--frames", eval_assets_frames, "Virtual frames A:B, A: or A")->capture_default_str();
    sub->add_option("--fit", eval_assets.fit_dir, "The fit (default: TAKE/derived/fit)");
    sub->add_option("--truth", eval_assets.truth_dir, "Ground truth (default: TAKE/ground_truth)");
    sub->add_flag("--json", eval_assets_json, "Print the table as JSON on stdout");
  }
  eval_textures->add_option("--textures", eval_assets.textures_dir, "The textures (default: TAKE/derived/textures)");

  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  if (auto s = stage::InitLogging(kProgram, log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  if (*photometric) {
    if (auto s = stage::ParseFrameRange("--frames", frames, &job.first_frame, &job.last_frame); !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    job.cameras = SplitCameras(cameras);
    job.geometry = stage::processing::GeometrySpec::Parse(geometry);
    stage::ProgressLine bar("camera frames");
    auto result = stage::processing::RunPhotometric(job, ShowOn(bar));
    bar.Finish();
    if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
    if (json) {
      std::cout << nlohmann::json{{"output_dir", result->output_dir}, {"units", result->units}}.dump() << "\n";
    } else {
      std::cout << result->units << " camera frame(s) processed into " << result->output_dir << "\n";
    }
    return 0;
  }
  if (*mvs.app) return mvs.Run();
  if (*fit.app) return fit.Run();
  if (*textures.app) return textures.Run();
  if (*stabilize.app) return stabilize.Run();
  if (asset.Parsed()) return asset.Run();
  if (graph.Parsed()) {
    return graph.Run([](const std::vector<std::string>& args) {
      std::vector<std::string> storage = {kProgram};
      storage.insert(storage.end(), args.begin(), args.end());
      std::vector<char*> stage_argv;
      for (std::string& a : storage) stage_argv.push_back(a.data());
      stage_argv.push_back(nullptr);
      return Dispatch(static_cast<int>(storage.size()), stage_argv.data());
    });
  }
  if (*calibrate) {
    if (auto s = stage::ParseFrameRange("--frames", cal_frames, &cal.options.first_frame, &cal.options.last_frame);
        !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    cal.options.cameras = SplitCameras(cal_cameras);
    stage::ProgressLine bar("cameras");
    auto report = stage::processing::RunCalibration(cal, ShowOn(bar));
    bar.Finish();
    if (!report.ok()) return stage::ReportFatal(kProgram, report.status());
    std::cout << (cal_json ? stage::processing::CalibrationReportJson(*report) + "\n"
                           : stage::processing::FormatCalibrationReport(*report));
    return 0;
  }
  if (*eval_calibration) {
    auto result = stage::processing::EvaluateCalibration(eval_cal_take, eval_cal_calibration);
    if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
    std::cout << (eval_cal_json ? stage::processing::CalibrationEvaluationJson(*result) + "\n"
                                : stage::processing::FormatTruthComparison(result->calibrated, &result->nominal));
    return 0;
  }
  if (*eval_mvs_app) {
    if (auto s = stage::ParseFrameRange("--frames", eval_mvs_frames, &eval_mvs.first_frame, &eval_mvs.last_frame);
        !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    auto result = stage::processing::EvaluateMvs(eval_mvs);
    if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
    if (!eval_mvs_pictures.empty()) {
      if (auto s = stage::processing::WriteMvsPictures(eval_mvs.take_dir, eval_mvs.results_dir, eval_mvs.first_frame,
                                                       eval_mvs_camera, eval_mvs_pictures);
          !s.ok()) {
        return stage::ReportFatal(kProgram, s);
      }
    }
    std::cout << (eval_mvs_json ? stage::processing::MvsEvaluationJson(*result) + "\n"
                                : stage::processing::FormatMvsEvaluation(*result));
    return 0;
  }
  if (*eval_fit || *eval_textures) {
    if (auto s =
            stage::ParseFrameRange("--frames", eval_assets_frames, &eval_assets.first_frame, &eval_assets.last_frame);
        !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    eval_assets.fit = eval_fit->parsed();
    eval_assets.textures = eval_textures->parsed();
    auto result = stage::processing::EvaluateAssets(eval_assets);
    if (!result.ok()) return stage::ReportFatal(kProgram, result.status());
    std::cout << (eval_assets_json ? stage::processing::AssetsEvaluationJson(*result) + "\n"
                                   : stage::processing::FormatAssetsEvaluation(*result));
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

int main(int argc, char** argv) {
  stage::ExecWithPassiveOpenMp(argv);  // torch's and Open3D's OpenMP loops
  return Dispatch(argc, argv);
}
