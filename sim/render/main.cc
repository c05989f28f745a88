// stage-sim-render: renders what one simulated camera sees under every pattern of the rig's set, without bringing a
// stage up, as a contact sheet PNG (and the raw frames as PGM), for people to look at the simulator.
#include <chrono>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/sim/ground_truth.h"
#include "stage/sim/performance_yaml.h"
#include "stage/sim/rendered_take.h"
#include "stage/sim/scene.h"
#include "stage/timing/schedule.h"

namespace {

constexpr const char* kProgram = "stage-sim-render";

// --range-of-motion-s: the head's range of motion of `seconds`, drawn from the rig's seed, written as
// DIR/range-of-motion.yaml, and named by the rig (an override added to `overrides`). The rig's own overrides must
// not name another performance.
absl::Status WriteRangeOfMotion(const stage::v1::RigConfig& rig, double seconds, const std::string& dir,
                                std::vector<std::string>* overrides) {
  if (dir.empty()) {
    return absl::InvalidArgumentError("--range-of-motion-s is for a take or a ground truth (--take, --ground-truth)");
  }
  for (const std::string& o : *overrides) {
    if (absl::StartsWith(o, "sim.subject.performance=")) {
      return absl::InvalidArgumentError(
          absl::StrCat("--range-of-motion-s writes its own performance: it takes no --set ", o));
    }
  }
  if (rig.sim().subject().kind() != "head") {
    return absl::InvalidArgumentError(absl::StrCat("--range-of-motion-s: the range of motion is a head's, not the ",
                                                   rig.sim().subject().kind(), "'s"));
  }
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::InternalError(absl::StrCat(dir, ": cannot create: ", ec.message()));
  const std::string path = std::filesystem::absolute(dir + "/range-of-motion.yaml").lexically_normal().string();
  const stage::sim::Performance performance = stage::sim::Performance::RangeOfMotion(rig.sim().seed(), seconds);
  if (auto s = stage::sim::WritePerformanceYaml(performance, path); !s.ok()) return s;
  overrides->push_back("sim.subject.performance=" + path);
  return absl::OkStatus();
}

// A raw frame as a viewable 8-bit BGR image: demosaiced, scaled so full-on white is near 80 % and gamma-encoded.
cv::Mat Viewable(const stage::sim::RawImage& raw, const stage::sim::SensorParams& sensor, double white_dn) {
  cv::Mat linear(raw.height, raw.width, CV_32F);
  for (int i = 0; i < raw.width * raw.height; ++i) {
    linear.at<float>(i / raw.width, i % raw.width) =
        static_cast<float>(std::max(0.0, (raw.data[static_cast<size_t>(i)] - sensor.black_level_dn) / white_dn));
  }
  cv::Mat bgr;
  if (sensor.mosaic == "mono") {
    cv::cvtColor(linear, bgr, cv::COLOR_GRAY2BGR);
  } else {
    cv::Mat raw16;
    linear.convertTo(raw16, CV_16U, 65535.0 / 2);  // headroom for highlights up to 2x white
    // GenICam's BayerRG (R at the first pixel) is OpenCV's BayerBG, and so on.
    const int code = sensor.mosaic == "RG"   ? cv::COLOR_BayerBG2BGR
                     : sensor.mosaic == "GR" ? cv::COLOR_BayerGB2BGR
                     : sensor.mosaic == "GB" ? cv::COLOR_BayerGR2BGR
                                             : cv::COLOR_BayerRG2BGR;
    cv::Mat bgr16;
    cv::cvtColor(raw16, bgr16, code);
    bgr16.convertTo(bgr, CV_32F, 2.0 / 65535.0);
  }
  cv::Mat out(bgr.size(), CV_8UC3);
  bgr.forEach<cv::Vec3f>([&](cv::Vec3f& v, const int* pos) {
    cv::Vec3b& o = out.at<cv::Vec3b>(pos[0], pos[1]);
    for (int c = 0; c < 3; ++c)
      o[c] = cv::saturate_cast<uint8_t>(255 * std::pow(std::clamp(0.8f * v[c], 0.f, 1.f), 1 / 2.2f));
  });
  return out;
}

// `stage-sim-render --take`: the take, its progress, and what was written as JSON.
int WriteTake(std::shared_ptr<const stage::sim::SimScene> scene, const std::string& dir,
              stage::sim::RenderedTakeOptions options, bool json) {
  stage::ProgressLine bar("camera frames");
  options.progress = [&bar](int64_t done, int64_t total) { bar.Update(done, total); };
  auto s = stage::sim::WriteRenderedTake(std::move(scene), dir, options);
  bar.Finish();
  if (!s.ok()) return stage::ReportFatal(kProgram, s);
  if (json) {
    std::cout << nlohmann::json({{"take", dir},
                                 {"first_frame", options.first_frame},
                                 {"last_frame", options.last_frame},
                                 {"frame_step", options.frame_step}})
                     .dump(2)
              << std::endl;
  }
  return 0;
}

// `stage-sim-render --ground-truth`: the truth, its progress, and what was written as JSON.
int WriteTruth(const stage::sim::SimScene& scene, const std::string& dir, stage::sim::GroundTruthOptions options,
               bool json) {
  options.progress = [](int done, int total) {
    std::cerr << "\rground truth: " << done << "/" << total << " camera frames" << (done == total ? "\n" : "")
              << std::flush;
  };
  if (auto s = stage::sim::WriteGroundTruth(scene, dir, options); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (json) {
    std::cout << nlohmann::json(
                     {{"ground_truth", dir}, {"first_frame", options.first_frame}, {"last_frame", options.last_frame}})
                     .dump(2)
              << std::endl;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Renders one simulated camera under every pattern of the rig's pattern set (steady light, the sensor "
      "model's noise) and writes a contact sheet PNG: what that camera would record in one cycle.",
      kProgram};
  stage::CommonFlags flags;
  stage::AddCommonFlags(app, &flags, /*serves=*/false);
  std::string camera_id;
  std::string out = "contact-sheet.png";
  int64_t frame = 0;
  int columns = 8;
  double tile_width = 0;
  bool json = false;
  std::vector<std::string> overrides;
  app.add_option("--camera", camera_id,
                 "Camera to render (default: the rig's first high-speed camera, else its first)");
  app.add_option("--frame", frame, "Virtual frame of the performance (the head's pose)")->capture_default_str();
  app.add_option("--out", out, "Contact sheet PNG to write")->capture_default_str();
  app.add_option("--columns", columns, "Tiles per row")->capture_default_str()->check(CLI::Range(1, 64));
  app.add_option("--tile-width", tile_width, "Width of a tile in pixels (0: as rendered)")->check(CLI::Range(0, 8192));
  app.add_option("--set", overrides, "Override a rig field, PATH=VALUE (e.g. sim.render_scale=0.25); repeatable");
  app.add_flag("--json", json, "Print what was rendered as JSON");
  std::string truth_dir, frames = "0:1";
  std::vector<std::string> truth_cameras;
  int uv_size = 256;
  app.add_option("--ground-truth", truth_dir,
                 "Write the ground truth (docs/simulator.md) to this directory instead of a contact sheet");
  app.add_option("--frames", frames, "Ground truth: virtual frames A:B (B excluded)")->capture_default_str();
  app.add_option("--cameras", truth_cameras, "Ground truth: these cameras only (default: all)")->delimiter(',');
  app.add_option("--uv-size", uv_size, "Ground truth: texels across the UV position map")
      ->capture_default_str()
      ->check(CLI::Range(16, 16384));
  int64_t frame_step = 1;
  bool no_camera_maps = false, no_meshes = false;
  app.add_option("--frame-step", frame_step, "Ground truth and take: every Nth frame of --frames")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{1}, int64_t{1} << 40));
  app.add_flag("--no-camera-maps", no_camera_maps,
               "Ground truth: no per-camera maps (the cameras, poses and UV position maps only)");
  app.add_flag("--no-meshes", no_meshes, "Ground truth: no mesh.obj per frame (uv_position.exr holds the surface)");
  bool uv_textures = false;
  app.add_flag("--uv-textures", uv_textures,
               "Ground truth and take: the skin's textures in the UV layout too (uv_albedo.exr, uv_material.exr, "
               "uv_normal.exr: what a neural asset's textures learn from)");
  std::string take_dir, take_cameras;
  bool all_patterns = false, take_truth_maps = false;
  app.add_option("--take", take_dir,
                 "Write a take (docs/asset.md#a-performance-to-learn-from) to this directory instead of a contact "
                 "sheet: each camera's frames of --frames (every --frame-step) in its frame file, take.json and the "
                 "ground truth (poses and UV position maps of --uv-size), without bringing the stage up");
  app.add_option("--take-cameras", take_cameras,
                 "Take: camera ids, comma-separated (default: every machine-vision camera)");
  app.add_flag("--all-patterns", all_patterns, "Take: every pattern of the cycle (default: the full-on ones only)");
  app.add_flag("--take-truth-maps", take_truth_maps,
               "Take: the ground truth's per-camera maps and a mesh per frame too (what `stage-process evaluate` "
               "compares with; default: poses and UV position maps only)");
  double range_of_motion_s = 0;
  app.add_option("--range-of-motion-s", range_of_motion_s,
                 "Take and ground truth: the head's range of motion for this many seconds (the rig's "
                 "range_of_motion is 180 s: more rounds of every group of expressions), drawn from sim.seed and "
                 "written as the performance file range-of-motion.yaml in the take's (or the truth's) directory, "
                 "which the rig then names")
      ->check(CLI::Range(6.0, 86400.0));
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  // The flags' own checks first: a command its flags refuse writes nothing (--range-of-motion-s's file; camera ids are
  // checked as the take or the truth is written).
  int64_t first_frame = 0, last_frame = 0;
  {
    const auto colon = frames.find(':');
    try {
      first_frame = std::stoll(frames.substr(0, colon));
      last_frame = colon == std::string::npos ? first_frame + 1 : std::stoll(frames.substr(colon + 1));
    } catch (const std::exception&) {
      return stage::ReportFatal(
          kProgram, absl::InvalidArgumentError(absl::StrCat("--frames \"", frames, "\" is not A:B (e.g. 0:24)")));
    }
    if (first_frame < 0 || last_frame <= first_frame) {
      return stage::ReportFatal(kProgram, absl::InvalidArgumentError(absl::StrCat(
                                              "--frames \"", frames, "\" holds no frame (A:B, 0 <= A < B)")));
    }
  }
  if (!take_dir.empty() && (!truth_dir.empty() || no_camera_maps || no_meshes || !truth_cameras.empty())) {
    return stage::ReportFatal(
        kProgram, absl::InvalidArgumentError("--take writes its own truth (poses and UV position maps): it takes no "
                                             "--ground-truth, --cameras, --no-camera-maps or --no-meshes"));
  }
  if (take_dir.empty() && (!take_cameras.empty() || all_patterns || take_truth_maps)) {
    return stage::ReportFatal(
        kProgram, absl::InvalidArgumentError("--take-cameras, --all-patterns and --take-truth-maps need --take"));
  }
  if (take_dir.empty() && truth_dir.empty() && frame_step != 1) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--frame-step needs --take or --ground-truth"));
  }
  auto loaded = stage::LoadRig(flags.config);
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  auto rig = stage::ApplyRigOverrides(*loaded, overrides);
  if (!rig.ok()) return stage::ReportFatal(kProgram, rig.status());
  if (range_of_motion_s > 0) {
    if (auto s = WriteRangeOfMotion(rig->rig, range_of_motion_s, take_dir.empty() ? truth_dir : take_dir, &overrides);
        !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    rig = stage::ApplyRigOverrides(*loaded, overrides);
    if (!rig.ok()) return stage::ReportFatal(kProgram, rig.status());
  }
  auto scene = stage::sim::SimScene::FromLoadedRig(*rig);
  if (!scene.ok()) return stage::ReportFatal(kProgram, scene.status());
  if (!take_dir.empty()) {
    stage::sim::RenderedTakeOptions options;
    options.first_frame = first_frame;
    options.last_frame = last_frame;
    options.frame_step = frame_step;
    options.cameras = absl::StrSplit(take_cameras, ',', absl::SkipEmpty());
    options.full_lit_only = !all_patterns;
    options.truth_camera_maps = take_truth_maps;
    options.truth_meshes = take_truth_maps;
    options.uv_size = uv_size;
    options.truth_textures = uv_textures;
    return WriteTake(*scene, take_dir, options, json);
  }
  if (!truth_dir.empty()) {
    stage::sim::GroundTruthOptions options;
    options.first_frame = first_frame;
    options.last_frame = last_frame;
    options.cameras = truth_cameras;
    options.uv_size = uv_size;
    options.frame_step = frame_step;
    options.camera_maps = !no_camera_maps;
    options.meshes = !no_meshes;
    options.uv_textures = uv_textures;
    return WriteTruth(**scene, truth_dir, options, json);
  }
  if (camera_id.empty()) {
    // The rig's first high-speed camera: the one that sees every pattern.
    for (const auto& c : rig->rig.cameras()) {
      if (camera_id.empty() && c.role() == stage::v1::CAMERA_ROLE_HIGH_SPEED) camera_id = c.id();
    }
    if (camera_id.empty() && rig->rig.cameras_size() > 0) camera_id = rig->rig.cameras(0).id();
    if (camera_id.empty()) {
      return stage::ReportFatal(kProgram,
                                absl::InvalidArgumentError(absl::StrCat(rig->source_name, " has no camera to render")));
    }
  }
  const int index = (*scene)->CameraIndex(camera_id);
  if (index < 0) {
    return stage::ReportFatal(
        kProgram, absl::NotFoundError(absl::StrCat("camera \"", camera_id, "\" is not in ", rig->source_name)));
  }
  stage::sim::CameraRenderer renderer(*scene, index);
  const auto t0 = std::chrono::steady_clock::now();
  auto responses = renderer.Responses(frame);
  const double precompute_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const auto& schedule = (*scene)->schedule();
  const int patterns = static_cast<int>(stage::timing::CycleLength(schedule));
  const auto& sensor = (*scene)->sensor(index);
  const double exposure_s = (*scene)->base().TicksToNs(schedule.cameras(index).exposure_ticks()) * 1e-9;
  const double white_dn = (*scene)->rig().sim().full_on_electrons() / sensor.Gain();
  std::vector<cv::Mat> tiles;
  const auto t1 = std::chrono::steady_clock::now();
  for (int p = 0; p < patterns; ++p) {
    const auto raw = renderer.Render((*scene)->PatternLevels(p), exposure_s, static_cast<uint64_t>(p), frame);
    cv::Mat tile = Viewable(raw, sensor, white_dn);
    if (tile_width > 0) {
      cv::resize(tile, tile,
                 cv::Size(static_cast<int>(tile_width), static_cast<int>(tile_width * tile.rows / tile.cols)), 0, 0,
                 cv::INTER_AREA);
    }
    cv::putText(tile, schedule.patterns(p).name(), cv::Point(4, tile.rows - 6), cv::FONT_HERSHEY_SIMPLEX,
                std::max(0.3, tile.cols / 400.0), cv::Scalar(255, 255, 255), 1, cv::LINE_AA);
    tiles.push_back(tile);
  }
  const double render_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
  const int rows = (patterns + columns - 1) / columns;
  cv::Mat sheet(rows * tiles[0].rows, columns * tiles[0].cols, CV_8UC3, cv::Scalar(40, 40, 40));
  for (int p = 0; p < patterns; ++p) {
    tiles[p].copyTo(
        sheet(cv::Rect((p % columns) * tiles[0].cols, (p / columns) * tiles[0].rows, tiles[0].cols, tiles[0].rows)));
  }
  if (!cv::imwrite(out, sheet)) {
    return stage::ReportFatal(kProgram, absl::UnavailableError(absl::StrCat(out, ": cannot write the PNG")));
  }
  if (json) {
    nlohmann::json j = {{"camera", camera_id},
                        {"frame", frame},
                        {"width", responses->width},
                        {"height", responses->height},
                        {"subject_pixels", responses->pixels.size()},
                        {"patterns", patterns},
                        {"precompute_s", precompute_s},
                        {"render_s_per_pattern", render_s / patterns},
                        {"out", out}};
    std::cout << j.dump(2) << std::endl;
  } else {
    std::cout << absl::StrCat(camera_id, ": ", responses->width, "x", responses->height, ", ", responses->pixels.size(),
                              " pixels on the subject; responses in ", precompute_s, " s, ", patterns, " patterns in ",
                              render_s, " s; wrote ", out)
              << std::endl;
  }
  return 0;
}
