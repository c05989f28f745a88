// Photometric stereo as a stage of the pipeline: see photometric_stage.h.
#include "stage/processing/photometric_stage.h"

#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/mesh.h"
#include "stage/common/status.h"
#include "stage/processing/calibration.h"
#include "stage/processing/fast_photometric.h"
#include "stage/processing/map_files.h"
#include "stage/processing/take_frames.h"
#include "stage/processing/visual_hull.h"
#include "statistics.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;

struct CameraJob {
  std::string id, path;
  FrameFileShape shape;
  CameraSetup setup;
  Image flat;
  bool has_flat = false;
  std::shared_ptr<const PhotometricTables> tables;  // the fast solver's, built at its first frame
  PhotometricMaps maps;                             // its maps, their memory reused frame to frame
};

// The flat field at the recorded size: as recorded, or the sensor's averaged down.
absl::StatusOr<Image> LoadFlatField(const std::string& path, int width, int height) {
  auto image = ReadImageFile(path);
  if (!image.ok()) return image.status();
  if (image->channels != 1) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": a flat field has one channel, not ", image->channels));
  }
  Image scaled = std::move(*image);
  if (scaled.width != width || scaled.height != height) {
    cv::Mat in(scaled.height, scaled.width, CV_32F, scaled.pixels.data()), out;
    cv::resize(in, out, {width, height}, 0, 0, cv::INTER_AREA);
    scaled = Image(width, height, 1);
    std::copy(out.ptr<float>(0), out.ptr<float>(0) + scaled.pixels.size(), scaled.pixels.begin());
  }
  for (float v : scaled.pixels) {
    if (!(v > 0.05f && v < 20.f))
      return absl::InvalidArgumentError(absl::StrCat(path, ": a flat field value ", v, " is not a relative response"));
  }
  return scaled;
}

// Pixels solved, and with a lobe.
std::pair<int64_t, int64_t> Solved(const PhotometricMaps& m) {
  int64_t solved = 0, specular = 0;
  for (uint8_t f : m.flags) {
    solved += (f & kLowSignal) == 0;
    specular += (f & (kLowSignal | kNoSpecular)) == 0;
  }
  return {solved, specular};
}

// How a unit's geometry was made: the pixels FillGeometry placed beyond the mesh, those RefillGeometry placed again,
// and those whose ray the frame's visual hull (of `hull_views` silhouettes; 0: none) bounded.
struct GeometryCounts {
  int64_t filled = 0, refilled = 0, hull_views = 0, hull_bounded = 0;
};

// A unit's metrics (metrics.json): what was solved and flagged, and typical values; deterministic.
std::string UnitMetrics(const PhotometricMaps& m, int64_t frame, const std::string& camera, const std::string& geometry,
                        const GeometryCounts& counts_of_geometry, const std::string& calibration) {
  const auto [solved, specular] = Solved(m);
  int64_t counts[6] = {0, 0, 0, 0, 0, 0};
  double confidence = 0;
  std::vector<float> albedo[3], rough, spec;
  for (size_t i = 0; i < m.flags.size(); ++i) {
    for (int b = 0; b < 6; ++b) counts[b] += (m.flags[i] >> b) & 1;
    if (m.flags[i] & kLowSignal) continue;
    confidence += m.confidence.pixels[i];
    for (int c = 0; c < 3; ++c) albedo[c].push_back(m.albedo.pixels[3 * i + c]);
    if (m.flags[i] & kNoSpecular) continue;
    rough.push_back(m.roughness.pixels[i]);
    spec.push_back(m.specular.pixels[i]);
  }
  nlohmann::ordered_json j;
  j["frame"] = frame;
  j["camera"] = camera;
  j["width"] = m.width;
  j["height"] = m.height;
  j["pixels_solved"] = solved;
  j["specular_pixels"] = specular;
  j["flags"] = {{"saturated", counts[0]}, {"low_signal", counts[1]},  {"bad_fit", counts[2]},
                {"shadowed", counts[3]},  {"no_specular", counts[4]}, {"specular_bad_fit", counts[5]}};
  j["mean_confidence"] = solved > 0 ? confidence / static_cast<double>(solved) : 0.0;
  j["median_albedo"] = {Median(albedo[0]), Median(albedo[1]), Median(albedo[2])};
  j["median_specular"] = Median(spec);
  j["median_roughness"] = Median(rough);
  j["geometry"] = geometry.empty() ? "none" : geometry;
  if (!geometry.empty()) {
    j["geometry_filled_pixels"] = counts_of_geometry.filled;
    j["geometry_refilled_pixels"] = counts_of_geometry.refilled;
    j["geometry_hull_views"] = counts_of_geometry.hull_views;
    j["geometry_hull_bounded_pixels"] = counts_of_geometry.hull_bounded;
  }
  j["calibration"] = calibration;
  return j.dump(2);
}

}  // namespace

std::string FrameDir(const std::string& root, int64_t frame) { return absl::StrFormat("%s/frame-%06d", root, frame); }

int64_t EndOfFrames(const std::string& root, const std::string& file, int64_t first) {
  int64_t end = first;
  while (fs::exists(FrameDir(root, end) + "/" + file)) ++end;
  return end;
}

std::string UnitDir(const std::string& root, int64_t frame, const std::string& camera) {
  return FrameDir(root, frame) + "/" + camera;
}

absl::StatusOr<LoadedRig> LoadTakeRig(const std::string& take_dir) {
  const std::string path = take_dir + "/take.json";
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open (is ", take_dir, " a take directory?)"));
  std::stringstream text;
  text << in.rdbuf();
  const nlohmann::json take = nlohmann::json::parse(text.str(), nullptr, /*allow_exceptions=*/false);
  if (take.is_discarded() || !take.contains("rig")) {
    return absl::DataLossError(absl::StrCat(path, ": not a take file (no \"rig\")"));
  }
  LoadedRig rig;
  google::protobuf::util::JsonParseOptions options;
  options.ignore_unknown_fields = false;
  const auto s = google::protobuf::util::JsonStringToMessage(take["rig"].dump(), &rig.rig, options);
  if (!s.ok()) return absl::DataLossError(absl::StrCat(path, ": its rig does not read: ", s.ToString()));
  rig.source_name = path;
  rig.base_dir = take_dir;
  return rig;
}

absl::StatusOr<std::optional<CameraCalibration>> LoadJobCalibration(const std::string& take_dir,
                                                                    const std::string& spec) {
  if (spec.empty()) return std::optional<CameraCalibration>();
  std::string path = PathInTake(take_dir, spec);
  if (fs::is_directory(path)) path += "/cameras.json";
  auto calibration = ReadCameraCalibration(path);
  if (!calibration.ok()) return calibration.status();
  if (calibration->source.empty()) calibration->source = path;
  return std::optional<CameraCalibration>(*std::move(calibration));
}

GeometrySpec GeometrySpec::Parse(const std::string& flag) {
  if (flag == "mvs") return {GeometrySource::kMvs, ""};
  if (flag == "none") return {GeometrySource::kNone, ""};
  return {GeometrySource::kDirectory, flag};
}

std::string GeometrySpec::ToString() const {
  switch (source) {
    case GeometrySource::kMvs:
      return "mvs";
    case GeometrySource::kNone:
      return "none";
    case GeometrySource::kDirectory:
      break;
  }
  return dir;
}

absl::Status GeometrySpec::Validate() const {
  if (source == GeometrySource::kDirectory && dir.empty()) {
    return absl::InvalidArgumentError("geometry: a directory of meshes needs its path");
  }
  if (source != GeometrySource::kDirectory && !dir.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("geometry: a directory (\"", dir, "\") is given with ", ToString(), " geometry"));
  }
  return absl::OkStatus();
}

std::string GeometrySpec::RelativeDir() const {
  if (source == GeometrySource::kNone) return "";
  return fs::path(source == GeometrySource::kMvs ? "derived/mvs" : dir).lexically_normal().string();
}

std::string GeometrySpec::Root(const std::string& take_dir) const { return PathInTake(take_dir, RelativeDir()); }

std::string PathInTake(const std::string& take_dir, const std::string& path, const std::string& fallback) {
  const std::string& p = path.empty() ? fallback : path;
  if (p.empty()) return "";
  return fs::path(p).is_absolute() ? p : take_dir + "/" + p;
}

absl::StatusOr<JobResult> RunPhotometric(const PhotometricJob& job,
                                         const std::function<void(const JobProgress&)>& progress,
                                         const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(job.options.Validate());
  STAGE_RETURN_IF_ERROR(job.geometry.Validate());
  auto rig = LoadTakeRig(job.take_dir);
  if (!rig.ok()) return rig.status();
  auto light = LightModel::FromRig(*rig);
  if (!light.ok()) return light.status();
  const int64_t cycle = static_cast<int64_t>(light->patterns.size());

  std::vector<std::string> ids = job.cameras;
  if (ids.empty()) {
    for (const v1::CameraConfig& c : rig->rig.cameras()) {
      if (c.role() == v1::CAMERA_ROLE_HIGH_SPEED) ids.push_back(c.id());
    }
    if (ids.empty())
      return absl::NotFoundError(absl::StrCat(job.take_dir, ": the take's rig has no high-speed camera"));
  }
  auto calibration = LoadJobCalibration(job.take_dir, job.calibration);
  if (!calibration.ok()) return calibration.status();
  std::vector<CameraJob> cameras;
  int64_t whole_frames = -1;
  for (const std::string& id : ids) {
    CameraJob c;
    c.id = id;
    c.path = job.take_dir + "/cameras/" + id + ".h5";
    if (!fs::exists(c.path)) {
      return absl::NotFoundError(absl::StrCat(c.path, ": no frame file for camera \"", id, "\" in the take"));
    }
    auto shape = ReadFrameFileShape(c.path);
    if (!shape.ok()) return shape.status();
    c.shape = *shape;
    auto setup = ResolveCamera(*rig, *light, id, shape->width, shape->height, shape->bits,
                               calibration->has_value() ? &**calibration : nullptr);
    if (!setup.ok()) return setup.status();
    c.setup = std::move(*setup);
    if (!c.setup.flat_field.empty()) {
      auto flat = LoadFlatField(c.setup.flat_field, shape->width, shape->height);
      if (!flat.ok()) return flat.status();
      c.flat = std::move(*flat);
      c.has_flat = true;
    }
    const int64_t frames = (shape->last_slot + 1) / cycle;
    whole_frames = whole_frames < 0 ? frames : std::min(whole_frames, frames);
    cameras.push_back(std::move(c));
  }
  const int64_t first = job.first_frame;
  const int64_t last = job.last_frame < 0 ? whole_frames : job.last_frame;
  if (first < 0 || last <= first || last > whole_frames) {
    return absl::InvalidArgumentError(absl::StrCat(job.take_dir, ": frames [", first, ", ", last, ") are ",
                                                   last <= first ? "empty" : "not all in the take", " (it holds ",
                                                   whole_frames, " whole frame(s))"));
  }
  // As given (relative to the take, or absolute), and as opened; empty without a mesh.
  const std::string geometry_dir = job.geometry.RelativeDir(), geometry_root = job.geometry.Root(job.take_dir);
  if (job.geometry.has_mesh()) {
    const bool mvs = job.geometry.source == GeometrySource::kMvs;
    if (!fs::is_directory(geometry_root)) {
      return absl::NotFoundError(
          mvs ? absl::StrCat(geometry_root,
                             ": no multi-view stereo meshes (the default geometry): run the mvs stage first "
                             "(stage-process mvs, stagectl process --stage mvs), or take --geometry none")
              : absl::StrCat(geometry_root, ": no such geometry directory"));
    }
  }
  JobResult result;
  result.output_dir = job.output_dir.empty() ? job.take_dir + "/derived/photometric" : job.output_dir;
  const int64_t total = (last - first) * static_cast<int64_t>(cameras.size());
  JobProgress p{0, total,
                absl::StrCat("photometric stereo: ", last - first, " frame(s) x ", cameras.size(), " camera(s)")};
  if (progress) progress(p);
  for (int64_t frame = first; frame < last; ++frame) {
    std::unique_ptr<MeshBvh> mesh;
    VisualHull hull;
    std::string geometry_file;
    if (!geometry_root.empty()) {
      auto obj = ReadObj(FrameDir(geometry_root, frame) + "/mesh.obj");
      if (!obj.ok()) return obj.status();
      mesh = std::make_unique<MeshBvh>(std::move(*obj));
      geometry_file = FrameDir(geometry_dir, frame) + "/mesh.obj";
      // The frame's visual hull, where the geometry has one (multi-view stereo's silhouettes).
      const std::string silhouettes = FrameDir(geometry_root, frame) + "/silhouette";
      if (job.options.geometry_hull && fs::exists(silhouettes + "/cameras.json")) {
        auto read = VisualHull::Read(silhouettes);
        if (!read.ok()) return read.status();
        hull = std::move(*read);
      }
    }
    for (CameraJob& c : cameras) {
      if (cancelled && cancelled()) {
        return absl::CancelledError(absl::StrCat("photometric stereo on ", job.take_dir, " cancelled after ",
                                                 result.units, " of ", total, " camera frame(s)"));
      }
      RawCorrection correction;
      correction.black_level_dn = c.setup.black_level_dn;
      if (c.has_flat) correction.flat_field = &c.flat;
      auto raw = LoadCycle(c.path, frame, *light);
      if (!raw.ok()) return raw.status();
      absl::Status status;
      GeometryCounts counts;
      counts.hull_views = static_cast<int64_t>(hull.views().size());
      PixelGeometry geometry;
      if (mesh == nullptr && !job.exact) {
        // Without geometry: the table-driven solver on the raw mosaic (the tables once per camera).
        if (c.tables == nullptr) {
          auto tables = PhotometricTables::Build(*light, c.setup.camera, job.options);
          if (!tables.ok()) return tables.status();
          c.tables = *tables;
        }
        status = SolvePhotometricFast(*light, *c.tables, *raw, correction, c.setup.camera, job.options, &c.maps);
      } else {
        auto frames = DemosaicCycle(*raw, correction);
        if (!frames.ok()) return frames.status();
        if (mesh != nullptr) {
          geometry = TraceGeometry(*mesh, c.setup.camera, c.shape.width, c.shape.height, *light,
                                   job.options.shadow_clearance_mm, job.options.threads);
          auto filled = FillGeometry(*mesh, c.setup.camera, *light, *frames, job.options, &geometry, &hull);
          if (!filled.ok()) return filled.status();
          counts.filled = *filled;
          for (float t : geometry.hull_in) counts.hull_bounded += t == t;
        }
        c.setup.camera.mosaic = raw->mosaic;  // the images' colours, as recorded
        auto solver = PhotometricSolver::Create(*light, *frames, c.setup.camera, job.options);
        if (!solver.ok()) return solver.status();
        const bool refill = mesh != nullptr && counts.filled > 0 && job.options.geometry_refill_passes > 0;
        auto maps = (*solver)->Solve(mesh != nullptr ? &geometry : nullptr, /*again=*/refill);
        for (int pass = 0; refill && maps.ok() && pass < job.options.geometry_refill_passes; ++pass) {
          auto refilled =
              RefillGeometry(*mesh, c.setup.camera, *light, maps->diffuse_normal_world, job.options, &geometry);
          if (!refilled.ok()) {
            maps = refilled.status();
            break;
          }
          counts.refilled = *refilled;
          // Only the placed pixels moved: only they are solved again.
          maps = (*solver)->SolveAgain(geometry, geometry.placed);
        }
        if (maps.ok()) c.maps = std::move(*maps);
        status = maps.status();
      }
      if (!status.ok()) {
        return absl::Status(status.code(),
                            absl::StrCat("frame ", frame, ", camera \"", c.id, "\": ", status.message()));
      }
      const PhotometricMaps* maps = &c.maps;
      const std::string dir = UnitDir(result.output_dir, frame, c.id);
      const std::string title =
          absl::StrFormat("%s  frame %d  %s  (geometry: %s)", fs::path(job.take_dir).filename().string(), frame, c.id,
                          geometry_file.empty() ? "none" : geometry_file);
      if (auto s =
              WriteMapFiles(dir, *maps, UnitMetrics(*maps, frame, c.id, geometry_file, counts, c.setup.source), title);
          !s.ok()) {
        return s;
      }
      if (mesh != nullptr) {
        if (auto s = WriteGeometryFiles(dir, geometry, c.setup.camera); !s.ok()) return s;
      }
      ++result.units;
      p.done = result.units;
      const auto [solved, specular] = Solved(*maps);
      p.message =
          absl::StrFormat("frame %d %s: %d pixels solved, a specular lobe on %d", frame, c.id, solved, specular);
      if (progress) progress(p);
    }
  }
  // What ran, for whoever reads the results (no times or hosts: the same job writes the same bytes).
  nlohmann::ordered_json run;
  run["stage"] = "photometric";
  run["take"] = fs::path(job.take_dir).filename().string();
  run["frames"] = {first, last};
  run["cameras"] = ids;
  run["geometry"] = job.geometry.ToString();
  run["cameras_placed_by"] =
      calibration->has_value() ? (*calibration)->source : "the rig's nominal models (uncalibrated)";
  run["solver"] = !job.geometry.has_mesh() && !job.exact ? "fast (tables, raw mosaic)" : "per pixel";
  run["options"] = {{"iterations", job.options.iterations},
                    {"table_size", job.options.table_size},
                    {"min_signal_dn", job.options.min_signal_dn},
                    {"min_signal_sigma", job.options.min_signal_sigma},
                    {"min_specular_snr", job.options.min_specular_snr},
                    {"max_specular_sigma_deg", job.options.max_specular_sigma_deg},
                    {"specular_filter_radius", job.options.specular_filter_radius},
                    {"shadow_clearance_mm", job.options.shadow_clearance_mm},
                    {"geometry_fill_px", job.options.geometry_fill_px},
                    {"geometry_refill_passes", job.options.geometry_refill_passes},
                    {"geometry_hull", job.options.geometry_hull},
                    {"geometry_hull_depth_mm", job.options.geometry_hull_depth_mm}};
  for (const CameraJob& c : cameras) {
    run["calibration"][c.id] = {{"source", c.setup.source},
                                {"white_scale", c.setup.camera.white_scale},
                                {"electrons_per_dn", c.setup.camera.gain_e_per_dn},
                                {"read_noise_e", c.setup.camera.read_noise_e},
                                {"black_level_dn", c.setup.black_level_dn},
                                {"cross_leakage", c.setup.camera.cross_leak},
                                {"flat_field", c.setup.flat_field.empty() ? "none" : c.setup.flat_field}};
  }
  if (auto s = WriteFileAtomically(result.output_dir + "/run.json", run.dump(2) + "\n"); !s.ok()) return s;
  return result;
}

}  // namespace stage::processing
