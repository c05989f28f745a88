// Multi-view stereo as a stage (mvs.h): the take's machine-vision frames read and undistorted, a depth map per view
// (mvs_depth.cc), filtered by agreement, fused and meshed (tsdf_fusion.cc), trimmed and written.
#include "stage/processing/mvs.h"

#include <chrono>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "mvs_internal.h"
#include "parallel.h"
#include "stage/common/file_util.h"
#include "stage/common/module.h"
#include "stage/common/status.h"
#include "stage/processing/calibration.h"
#include "stage/processing/light_model.h"
#include "stage/processing/map_files.h"
#include "stage/processing/take_frames.h"
#include "stage/processing/visual_hull.h"
#include "statistics.h"

namespace stage::processing {

absl::StatusOr<TriangleMesh> FuseDepthMaps(const std::vector<MvsView>& views, const std::vector<DepthMap>& depths,
                                           double voxel_mm, const MvsOptions& options) {
  static const absl::StatusOr<FuseDepthMapsFn> fuse = OpenModuleAs<FuseDepthMapsFn>(
      {.target = kTsdfFusionTarget, .entry = kTsdfFusionEntry, .what = "the depth maps' fusion module"});
  if (!fuse.ok()) return fuse.status();
  return (*fuse)(views, depths, voxel_mm, options);
}

namespace {

namespace fs = std::filesystem;

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

// A pixel's footprint at the volume's centre in the median view, mm.
double PixelFootprint(const std::vector<MvsView>& views, const MvsOptions& o) {
  std::vector<double> footprint;
  for (const MvsView& v : views) footprint.push_back((v.position - o.volume_centre_mm).norm() / v.fx);
  return Median(footprint);
}

// The voxel: options.voxel_mm, or voxel_px footprints of a pixel, at least 0.2 mm.
double VoxelSize(double pixel_mm, const MvsOptions& o) {
  if (o.voxel_mm > 0) return o.voxel_mm;
  return std::max(0.2, o.voxel_px * pixel_mm);
}

absl::StatusOr<std::vector<MvsCamera>> JobCameras(const MvsJob& job, const LoadedRig& rig,
                                                  const CameraCalibration* calibration) {
  std::vector<std::string> ids = job.cameras;
  if (ids.empty()) {
    for (const v1::CameraConfig& c : rig.rig.cameras()) {
      if (c.role() == v1::CAMERA_ROLE_MACHINE_VISION) ids.push_back(c.id());
    }
  }
  if (ids.size() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(job.take_dir, ": multi-view stereo needs 2 cameras or more, ", ids.size(), " given"));
  }
  return OpenTakeCameras(job.take_dir, rig, ids, calibration);
}

// A view's map (`map`, in its undistorted pixels: `width` x `height`) at the pixels of the image as recorded (with its
// lens's distortion), at the processing size: `camera` is the recorded camera at that size. Pixels whose undistorted
// place falls outside the map keep `outside`.
template <typename T>
std::vector<T> AsRecorded(const std::vector<T>& map, int width, int height, const CameraModel& camera, T outside) {
  std::vector<cv::Point2f> pixels;
  pixels.reserve(static_cast<size_t>(camera.width()) * camera.height());
  for (int y = 0; y < camera.height(); ++y) {
    for (int x = 0; x < camera.width(); ++x) pixels.emplace_back(static_cast<float>(x), static_cast<float>(y));
  }
  const cv::Matx33d k(camera.fx(), 0, camera.cx(), 0, camera.fy(), camera.cy(), 0, 0, 1);
  const auto& d = camera.distortion();
  std::vector<cv::Point2f> undistorted;
  cv::undistortPoints(pixels, undistorted, k, std::vector<double>(d.begin(), d.end()), cv::noArray(), k);
  std::vector<T> out(pixels.size(), outside);
  for (size_t i = 0; i < undistorted.size(); ++i) {
    const int u = static_cast<int>(std::lround(undistorted[i].x)), v = static_cast<int>(std::lround(undistorted[i].y));
    if (u < 0 || v < 0 || u >= width || v >= height) continue;
    out[i] = map[static_cast<size_t>(v) * width + u];
  }
  return out;
}

Image DepthAsRecorded(const DepthMap& depth, const CameraModel& camera) {
  Image out(camera.width(), camera.height(), 1);
  out.pixels = AsRecorded(depth.depth, depth.width, depth.height, camera, 0.0f);
  return out;
}

// The views' silhouettes (SilhouetteMask of their full-lit images at the processing size), as recorded.
std::vector<Silhouette> Silhouettes(const std::vector<MvsView>& views, const std::vector<CameraModel>& processed,
                                    const MvsOptions& options) {
  std::vector<Silhouette> out(views.size());
  internal::ParallelItems(static_cast<int>(views.size()), options.threads, [&](int i) {
    const MvsView& v = views[static_cast<size_t>(i)];
    // The background's bar as the sweep's (SweepDepth): a fraction of the image's 99th percentile.
    const float bar = static_cast<float>(options.min_signal) * static_cast<float>(Quantile(v.grey, 99, 100));
    const std::vector<uint8_t> mask = SilhouetteMask(v.grey, v.width, v.height, bar, options.silhouette_grow_px);
    // A recorded pixel the undistorted view does not hold (a corner, under barrel distortion) is no evidence of
    // background: inside.
    out[static_cast<size_t>(i)] = {v.id, processed[static_cast<size_t>(i)],
                                   AsRecorded(mask, v.width, v.height, processed[static_cast<size_t>(i)], uint8_t{1})};
  });
  return out;
}

std::string FrameMetrics(const MvsFrame& f, int64_t frame, const std::vector<std::string>& missing) {
  nlohmann::ordered_json j;
  j["frame"] = frame;
  j["views"] = nlohmann::json::array();
  for (const MvsViewMetrics& v : f.views) {
    j["views"].push_back({{"camera", v.id},
                          {"neighbours", v.neighbours},
                          {"foreground_pixels", v.foreground},
                          {"matched_pixels", v.matched},
                          {"consistent_pixels", v.consistent}});
  }
  j["cameras_without_a_full_lit_frame"] = missing;
  j["pixel_mm"] = f.pixel_mm;
  j["min_score"] = f.min_score;
  j["voxel_mm"] = f.voxel_mm;
  j["mesh"] = {{"vertices", f.mesh.positions.size()},
               {"triangles", f.mesh.triangles.size()},
               {"vertices_before_trim", f.mesh_vertices_before_trim},
               {"holes_filled", f.holes_filled},
               {"filled_mm2", f.filled_mm2}};
  return j.dump(2) + "\n";
}

absl::Status WriteFrame(const std::string& dir, const MvsFrame& f, const FrameViews& in, const MvsOptions& options,
                        int64_t frame, const std::string& take) {
  const std::vector<CameraModel>& processed = in.processed;
  std::error_code ec;
  fs::create_directories(dir + "/depth", ec);
  if (ec) return absl::InternalError(absl::StrCat(dir, "/depth: cannot create: ", ec.message()));
  for (size_t i = 0; i < f.depths.size(); ++i) {
    STAGE_RETURN_IF_ERROR(
        WriteExr(dir + "/depth/" + f.views[i].id + ".exr", DepthAsRecorded(f.depths[i], processed[i])));
  }
  STAGE_RETURN_IF_ERROR(
      WriteObj(dir + "/mesh.obj", f.mesh,
               absl::StrFormat("FaStage multi-view stereo: %s frame %d, stage frame, mm", take, frame)));
  STAGE_RETURN_IF_ERROR(VisualHull::Write(dir + "/silhouette", Silhouettes(in.views, processed, options)));
  return WriteFileAtomically(dir + "/metrics.json", FrameMetrics(f, frame, in.missing));
}

}  // namespace

absl::Status ReadFrameViews(const MvsTake& take, int64_t frame, double scale, FrameViews* out) {
  for (const MvsCamera& c : take.cameras) {
    bool found = false;
    STAGE_RETURN_IF_ERROR(ForEachFullLitFrame(
        c.path, frame, frame + 1, take.light, c.black_level_dn, [&](int64_t, const Image& grey) -> absl::Status {
          STAGE_ASSIGN_OR_RETURN(MvsView v, MakeMvsView(c.id, grey, c.model, scale));
          out->processed.push_back(c.model.Resized(v.width, v.height));
          out->views.push_back(std::move(v));
          found = true;
          return absl::OkStatus();
        }));
    if (!found) out->missing.push_back(c.id);
  }
  return absl::OkStatus();
}

absl::StatusOr<MvsTake> OpenMvsTake(const MvsJob& job) {
  STAGE_ASSIGN_OR_RETURN(const LoadedRig rig, LoadTakeRig(job.take_dir));
  MvsTake take;
  STAGE_ASSIGN_OR_RETURN(take.light, LightModel::FromRig(rig));
  STAGE_ASSIGN_OR_RETURN(take.calibration, LoadJobCalibration(job.take_dir, job.calibration));
  STAGE_ASSIGN_OR_RETURN(take.cameras,
                         JobCameras(job, rig, take.calibration.has_value() ? &*take.calibration : nullptr));
  const int64_t cycle = static_cast<int64_t>(take.light.patterns.size());
  // A machine-vision camera records one slot of a frame's cycle: the frames are those its slots fall in.
  for (const MvsCamera& c : take.cameras) {
    take.frames = std::max(take.frames, c.last_slot < 0 ? 0 : c.last_slot / cycle + 1);
  }
  return take;
}

namespace {

// What ran, for whoever reads the results (no times or hosts: the same job writes the same bytes).
std::string RunJson(const MvsJob& job, const std::string& take, int64_t first, int64_t last,
                    const std::vector<MvsCamera>& cameras, const std::optional<CameraCalibration>& calibration) {
  const MvsOptions& o = job.options;
  nlohmann::ordered_json run;
  run["stage"] = "mvs";
  run["take"] = take;
  run["frames"] = {first, last};
  std::vector<std::string> ids;
  for (const MvsCamera& c : cameras) ids.push_back(c.id);
  run["cameras"] = ids;
  run["cameras_placed_by"] = calibration.has_value() ? calibration->source : "the rig's nominal models (uncalibrated)";
  run["calibration"] = job.calibration;  // as named (MvsJob::calibration): evaluation finds its frame from it
  run["options"] = {{"image_scale", o.image_scale},
                    {"neighbours", o.neighbours},
                    {"best_of", o.best_of},
                    {"angles_deg", {o.min_angle_deg, o.max_angle_deg}},
                    {"window", o.window},
                    {"coarse_width", o.coarse_width},
                    {"refine_steps", o.refine_steps},
                    {"prior_median_radius", o.prior_median_radius},
                    {"min_score", o.min_score},
                    {"fine_min_score", o.fine_min_score},
                    {"fine_footprint_mm", o.fine_footprint_mm},
                    {"keep_coarser", o.keep_coarser},
                    {"min_signal", o.min_signal},
                    {"silhouette_grow_px", o.silhouette_grow_px},
                    {"min_consistent", o.min_consistent},
                    {"consistency_px", o.consistency_px},
                    {"volume_centre_mm", {o.volume_centre_mm.x(), o.volume_centre_mm.y(), o.volume_centre_mm.z()}},
                    {"volume_radius_mm", o.volume_radius_mm},
                    {"voxel_mm", o.voxel_mm},
                    {"voxel_px", o.voxel_px},
                    {"truncation_voxels", o.truncation_voxels},
                    {"min_views", o.min_views},
                    {"fill_holes_mm", o.fill_holes_mm},
                    {"smooth_iterations", o.smooth_iterations}};
  return run.dump(2) + "\n";
}

}  // namespace

absl::Status MvsOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("mvs options: ", what)); };
  if (!(image_scale > 0 && image_scale <= 1))
    return bad(absl::StrCat("image_scale ", image_scale, " is not in (0, 1]"));
  if (neighbours < 1 || neighbours > 16) return bad(absl::StrCat("neighbours ", neighbours, " is not in 1..16"));
  if (best_of < 1 || best_of > neighbours) return bad(absl::StrCat("best_of ", best_of, " is not in 1..neighbours"));
  if (!(min_angle_deg >= 0 && max_angle_deg > min_angle_deg && max_angle_deg < 90)) {
    return bad(absl::StrCat("angles [", min_angle_deg, ", ", max_angle_deg, "] are not 0 <= min < max < 90"));
  }
  if (window < 3 || window % 2 == 0 || window > 31) return bad(absl::StrCat("window ", window, " is not odd in 3..31"));
  if (coarse_width < 16) return bad(absl::StrCat("coarse_width ", coarse_width, " is below 16"));
  if (refine_steps < 1 || refine_steps > 16)
    return bad(absl::StrCat("refine_steps ", refine_steps, " is not in 1..16"));
  if (prior_median_radius < 0 || prior_median_radius > 8) {
    return bad(absl::StrCat("prior_median_radius ", prior_median_radius, " is not in 0..8"));
  }
  if (!(min_score > -1 && min_score < 1)) return bad(absl::StrCat("min_score ", min_score, " is not in (-1, 1)"));
  if (!(fine_min_score > -1 && fine_min_score < 1)) {
    return bad(absl::StrCat("fine_min_score ", fine_min_score, " is not in (-1, 1)"));
  }
  if (!(fine_footprint_mm >= 0)) return bad(absl::StrCat("fine_footprint_mm ", fine_footprint_mm, " is negative"));
  if (!(min_signal >= 0 && min_signal < 1)) return bad(absl::StrCat("min_signal ", min_signal, " is not in [0, 1)"));
  if (min_consistent < 0 || min_consistent > neighbours) {
    return bad(absl::StrCat("min_consistent ", min_consistent, " is not in 0..neighbours"));
  }
  if (!(consistency_px > 0)) return bad(absl::StrCat("consistency_px ", consistency_px, " is not positive"));
  if (!(volume_radius_mm > 0)) return bad(absl::StrCat("volume_radius_mm ", volume_radius_mm, " is not positive"));
  if (!(voxel_mm >= 0) || !(voxel_px > 0)) return bad("voxel_mm must be >= 0 and voxel_px > 0");
  if (!(truncation_voxels >= 1)) return bad(absl::StrCat("truncation_voxels ", truncation_voxels, " is below 1"));
  if (smooth_iterations < 0 || smooth_iterations > 1000) {
    return bad(absl::StrCat("smooth_iterations ", smooth_iterations, " is not in 0..1000"));
  }
  if (silhouette_grow_px < 0 || silhouette_grow_px > 16) {
    return bad(absl::StrCat("silhouette_grow_px ", silhouette_grow_px, " is not in 0..16"));
  }
  if (!(fill_holes_mm >= 0)) return bad(absl::StrCat("fill_holes_mm ", fill_holes_mm, " is negative"));
  if (min_views < 1) return bad(absl::StrCat("min_views ", min_views, " is below 1"));
  if (threads < 0) return bad(absl::StrCat("threads ", threads, " is negative"));
  return absl::OkStatus();
}

absl::StatusOr<MvsView> MakeMvsView(const std::string& id, const Image& grey, const CameraModel& camera, double scale) {
  if (grey.channels != 1 || grey.width != camera.width() || grey.height != camera.height()) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", id, "\": image ", grey.width, "x", grey.height, "x",
                                                   grey.channels, ", its model ", camera.width(), "x", camera.height(),
                                                   "x1"));
  }
  const int w = std::max(16, static_cast<int>(std::lround(grey.width * scale)));
  const int h = std::max(16, static_cast<int>(std::lround(grey.height * scale)));
  const CameraModel at = camera.Resized(w, h);
  cv::Mat in(grey.height, grey.width, CV_32F, const_cast<float*>(grey.pixels.data())), resized, out;
  if (w == grey.width && h == grey.height) {
    resized = in;
  } else {
    cv::resize(in, resized, {w, h}, 0, 0, cv::INTER_AREA);
  }
  const cv::Matx33d k(at.fx(), 0, at.cx(), 0, at.fy(), at.cy(), 0, 0, 1);
  const auto& d = at.distortion();
  cv::undistort(resized, out, k, std::vector<double>(d.begin(), d.end()), k);
  MvsView v;
  v.id = id;
  v.width = w;
  v.height = h;
  v.fx = at.fx(), v.fy = at.fy(), v.cx = at.cx(), v.cy = at.cy();
  v.rotation = at.rotation();
  v.position = at.position();
  v.grey.assign(out.ptr<float>(0), out.ptr<float>(0) + static_cast<size_t>(w) * h);
  return v;
}

absl::StatusOr<MvsFrame> ReconstructFrame(const std::vector<MvsView>& views, const MvsOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (views.size() < 2)
    return absl::InvalidArgumentError(absl::StrCat("multi-view stereo needs 2 views, got ", views.size()));
  for (const MvsView& v : views) {
    if (v.width < 16 || v.height < 16 || v.grey.size() != static_cast<size_t>(v.width) * v.height || v.fx <= 0 ||
        v.fy <= 0) {
      return absl::InvalidArgumentError(absl::StrCat("view \"", v.id, "\": no image or no intrinsics"));
    }
  }
  MvsFrame f;
  f.pixel_mm = PixelFootprint(views, options);
  MvsOptions o = options;
  if (f.pixel_mm < options.fine_footprint_mm) o.min_score = options.fine_min_score;
  f.min_score = o.min_score;
  const auto neighbours = ChooseNeighbours(views, options);
  for (size_t i = 0; i < views.size(); ++i) {
    if (neighbours[i].empty()) {
      return absl::FailedPreconditionError(absl::StrCat("view \"", views[i].id, "\": no other view within ",
                                                        options.min_angle_deg, "-", options.max_angle_deg,
                                                        " degrees of its axis"));
    }
  }
  const int n = static_cast<int>(views.size());
  f.views.resize(n);
  std::vector<DepthMap> raw(n);
  auto t0 = std::chrono::steady_clock::now();
  internal::ParallelItems(n, options.threads, [&](int i) {
    f.views[i].id = views[i].id;
    for (int j : neighbours[i]) f.views[i].neighbours.push_back(views[j].id);
    raw[i] = SweepDepth(views, i, neighbours[i], o, &f.views[i]);
  });
  f.depths.resize(n);
  internal::ParallelItems(n, options.threads, [&](int i) {
    f.views[i].consistent = KeepConsistent(views, raw, i, neighbours[i], options, &f.depths[i]);
  });
  f.depth_s = Seconds(t0);
  t0 = std::chrono::steady_clock::now();
  f.voxel_mm = VoxelSize(f.pixel_mm, options);
  STAGE_ASSIGN_OR_RETURN(TriangleMesh fused, FuseDepthMaps(views, f.depths, f.voxel_mm, options));
  f.fusion_s = Seconds(t0);
  t0 = std::chrono::steady_clock::now();
  f.mesh_vertices_before_trim = static_cast<int64_t>(fused.positions.size());
  f.mesh = TrimToHead(fused, options.volume_centre_mm, options.volume_radius_mm);
  const HoleFill filled = FillHoles(options.fill_holes_mm, &f.mesh);
  f.holes_filled = filled.holes;
  f.filled_mm2 = filled.area_mm2;
  SmoothMesh(options.smooth_iterations, &f.mesh);
  f.mesh_s = Seconds(t0);
  return f;
}

absl::StatusOr<JobResult> RunMvs(const MvsJob& job, const std::function<void(const JobProgress&)>& progress,
                                 const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(job.options.Validate());
  STAGE_ASSIGN_OR_RETURN(const MvsTake in_take, OpenMvsTake(job));
  const std::vector<MvsCamera>& cameras = in_take.cameras;
  const int64_t whole = in_take.frames;
  const int64_t first = job.first_frame, last = job.last_frame < 0 ? whole : job.last_frame;
  if (first < 0 || last <= first || last > whole) {
    return absl::InvalidArgumentError(absl::StrCat(job.take_dir, ": frames [", first, ", ", last, ") are ",
                                                   last <= first ? "empty" : "not all in the take", " (it holds ",
                                                   whole, " frame(s))"));
  }
  JobResult result;
  result.output_dir = job.output_dir.empty() ? job.take_dir + "/derived/mvs" : job.output_dir;
  const std::string take = fs::path(job.take_dir).filename().string();
  JobProgress p{0, last - first,
                absl::StrCat("multi-view stereo: ", last - first, " frame(s) x ", cameras.size(), " camera(s)")};
  if (progress) progress(p);
  for (int64_t frame = first; frame < last; ++frame) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(
          absl::StrCat("multi-view stereo on ", job.take_dir, " cancelled after ", result.units, " frame(s)"));
    }
    FrameViews in;
    STAGE_RETURN_IF_ERROR(ReadFrameViews(in_take, frame, job.options.image_scale, &in));
    auto made = ReconstructFrame(in.views, job.options);
    if (!made.ok()) {
      return absl::Status(made.status().code(),
                          absl::StrCat(job.take_dir, ": frame ", frame, ": ", made.status().message()));
    }
    const std::string dir = FrameDir(result.output_dir, frame);
    STAGE_RETURN_IF_ERROR(WriteFrame(dir, *made, in, job.options, frame, take));
    ++result.units;
    p.done = result.units;
    p.message = absl::StrFormat("frame %d: %d views, mesh of %d vertices (depth %.1f s, fusion %.1f s)", frame,
                                in.views.size(), made->mesh.positions.size(), made->depth_s, made->fusion_s);
    if (progress) progress(p);
  }
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/run.json",
                                            RunJson(job, take, first, last, cameras, in_take.calibration)));
  return result;
}

}  // namespace stage::processing
