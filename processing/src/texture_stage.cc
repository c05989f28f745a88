// Texture fusion as a stage: the fitted template and the views' photometric maps of every frame of a take, fused
// and written (docs/assets.md#texture-fusion-as-a-stage).
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/calibration.h"
#include "stage/processing/map_files.h"
#include "stage/processing/texture_fusion.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;

}  // namespace

absl::StatusOr<Eigen::Isometry3f> HeadFromStage(const std::string& pose_file) {
  std::ifstream in(pose_file);
  if (!in) return absl::NotFoundError(absl::StrCat(pose_file, ": cannot open the pose (stage_from_head)"));
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.contains("stage_from_head") || !j["stage_from_head"].is_array() ||
      j["stage_from_head"].size() != 16) {
    return absl::InvalidArgumentError(absl::StrCat(pose_file, ": stage_from_head is not 16 numbers"));
  }
  Eigen::Matrix4f m;
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) m(r, c) = j["stage_from_head"][static_cast<size_t>(4 * r + c)].get<float>();
  }
  Eigen::Isometry3f stage_from_head;
  stage_from_head.matrix() = m;
  return stage_from_head.inverse();
}

absl::StatusOr<FusionView> LoadFusionView(const LoadedRig& rig, const CameraCalibration* calibration,
                                          const std::string& dir, const std::string& id) {
  FusionView v;
  v.camera_id = id;
  struct Entry {
    const char* file;
    Image* image;
    bool required;
  };
  for (const Entry& e :
       {Entry{"albedo", &v.albedo, true}, Entry{"diffuse_normal_world", &v.diffuse_normal, true},
        Entry{"specular", &v.specular, false}, Entry{"roughness", &v.roughness, false},
        Entry{"specular_normal_world", &v.specular_normal, false}, Entry{"confidence", &v.confidence, false}}) {
    const std::string path = dir + "/" + e.file + ".exr";
    if (!e.required && !fs::exists(path)) continue;
    auto image = ReadImageFile(path);
    if (!image.ok()) return image.status();
    *e.image = *std::move(image);
  }
  STAGE_ASSIGN_OR_RETURN(v.camera, CameraAtImageSize(rig, id, v.albedo.width, v.albedo.height, calibration));
  return v;
}

namespace {

std::string MetricsJson(int64_t frame, const FusedTextures& t, const std::vector<FusionView>& views) {
  nlohmann::ordered_json j;
  j["frame"] = frame;
  j["size"] = t.size;
  int64_t covered = 0, dilated = 0, lobe = 0, overlap = 0;
  for (size_t i = 0; i < t.state.size(); ++i) {
    covered += t.state[i] == TexelState::kCovered;
    dilated += t.state[i] == TexelState::kDilated;
    lobe += t.specular_weight.pixels[i] > 0;
    overlap += t.views[i] >= 2;
  }
  j["texels_covered"] = covered;
  j["texels_dilated"] = dilated;
  j["texels_seen_twice"] = overlap;
  j["texels_with_a_lobe"] = lobe;
  j["lobes_rejected"] = t.lobes_rejected;
  for (size_t i = 0; i < views.size(); ++i) j["texels_per_view"][views[i].camera_id] = t.texels_per_view[i];
  return j.dump(2);
}

std::string RunJson(const TexturesJob& job, const std::vector<std::string>& cameras, int64_t last) {
  nlohmann::ordered_json run;
  run["stage"] = "textures";
  run["take"] = fs::path(job.take_dir).filename().string();
  run["frames"] = {job.first_frame, last};
  run["cameras"] = cameras;
  run["calibration"] = job.calibration.empty() ? "the rig's nominal models (uncalibrated)" : job.calibration;
  run["fit"] = job.fit_dir.empty() ? "derived/fit" : job.fit_dir;
  run["photometric"] = job.photometric_dir.empty() ? "derived/photometric" : job.photometric_dir;
  const FusionOptions& o = job.options;
  run["options"] = {{"size", o.size},
                    {"part", o.part},
                    {"max_view_angle_deg", o.max_view_angle_deg},
                    {"max_lobe_view_angle_deg", o.max_lobe_view_angle_deg},
                    {"min_confidence", o.min_confidence},
                    {"feather_px", o.feather_px},
                    {"occlusion_mm", o.occlusion_mm},
                    {"contour_mm", o.contour_mm},
                    {"dilation_px", o.dilation_px}};
  return run.dump(2) + "\n";
}

// The cameras with maps in `frame_dir` (its subdirectories), sorted.
std::vector<std::string> CamerasIn(const std::string& frame_dir) {
  std::vector<std::string> ids;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(frame_dir, ec)) {
    if (entry.is_directory() && fs::exists(entry.path() / "albedo.exr")) ids.push_back(entry.path().filename());
  }
  std::sort(ids.begin(), ids.end());
  return ids;
}

// The frames the job covers: [first_frame, last); an open range ends at the fit's first missing frame.
absl::StatusOr<int64_t> LastFrame(const TexturesJob& job, const std::string& fit) {
  const int64_t last = job.last_frame >= 0 ? job.last_frame : EndOfFrames(fit, "mesh.obj", job.first_frame);
  if (last <= job.first_frame) {
    return absl::InvalidArgumentError(absl::StrCat(fit, ": no fitted frames [", job.first_frame, ", ", last, ")"));
  }
  return last;
}

// Fuses one frame's views and writes its textures.
absl::Status FuseFrame(const TexturesJob& job, const LoadedRig& rig, const CameraCalibration* calibration,
                       const std::string& fit, const std::string& maps, const std::vector<std::string>& cameras,
                       int64_t frame, const std::string& output_dir) {
  STAGE_ASSIGN_OR_RETURN(const TriangleMesh mesh, ReadObj(FrameDir(fit, frame) + "/mesh.obj"));
  STAGE_ASSIGN_OR_RETURN(const Eigen::Isometry3f head_from_stage, HeadFromStage(FrameDir(fit, frame) + "/pose.json"));
  std::vector<FusionView> views;
  for (const std::string& id : cameras) {
    auto view = LoadFusionView(rig, calibration, UnitDir(maps, frame, id), id);
    if (!view.ok()) return view.status();
    views.push_back(*std::move(view));
  }
  auto fused = FuseTextures(mesh, head_from_stage, views, job.options);
  if (!fused.ok()) {
    return absl::Status(fused.status().code(),
                        absl::StrCat(job.take_dir, ": frame ", frame, ": ", fused.status().message()));
  }
  return WriteFusedTextures(FrameDir(output_dir, frame), *fused, MetricsJson(frame, *fused, views),
                            absl::StrFormat("frame %d: %d views fused", frame, views.size()));
}

// The textures' files, in the order they are written.
std::vector<std::pair<std::string, Image FusedTextures::*>> TextureFiles() {
  return {{"albedo", &FusedTextures::albedo},
          {"specular", &FusedTextures::specular},
          {"roughness", &FusedTextures::roughness},
          {"normal_object", &FusedTextures::normal_object},
          {"normal_tangent", &FusedTextures::normal_tangent},
          {"specular_normal_object", &FusedTextures::specular_normal_object},
          {"specular_normal_tangent", &FusedTextures::specular_normal_tangent},
          {"weight", &FusedTextures::weight},
          {"specular_weight", &FusedTextures::specular_weight}};
}

}  // namespace

absl::Status WriteFusedTextures(const std::string& dir, const FusedTextures& textures, const std::string& metrics_json,
                                const std::string& title) {
  std::vector<std::pair<std::string, const Image*>> files;
  for (const auto& [name, member] : TextureFiles()) files.emplace_back(name, &(textures.*member));
  return WriteTextureFiles(dir, files, metrics_json, title);
}

absl::StatusOr<FusedTextures> ReadFusedTextures(const std::string& dir) {
  FusedTextures t;
  for (const auto& [name, member] : TextureFiles()) {
    STAGE_ASSIGN_OR_RETURN(t.*member, ReadImageFile(dir + "/" + name + ".exr"));
  }
  t.size = t.albedo.width;
  const size_t n = static_cast<size_t>(t.size) * t.size;
  for (const auto& [name, member] : TextureFiles()) {
    const Image& image = t.*member;
    if (image.width != t.size || image.height != t.size) {
      return absl::DataLossError(absl::StrFormat("%s/%s.exr: %d x %d, not the albedo's %d x %d", dir, name, image.width,
                                                 image.height, t.size, t.size));
    }
  }
  t.state.assign(n, TexelState::kEmpty);
  for (size_t i = 0; i < n; ++i) {
    const float* normal = &t.normal_object.pixels[3 * i];
    if (t.weight.pixels[i] > 0) {
      t.state[i] = TexelState::kCovered;
    } else if (normal[0] != 0 || normal[1] != 0 || normal[2] != 0) {
      t.state[i] = TexelState::kDilated;
    }
  }
  return t;
}

absl::Status TexturesJob::Validate() const {
  if (take_dir.empty()) return absl::InvalidArgumentError("textures: no take directory");
  if (first_frame < 0) return absl::InvalidArgumentError(absl::StrCat("textures: first frame ", first_frame, " < 0"));
  if (last_frame >= 0 && last_frame <= first_frame) {
    return absl::InvalidArgumentError(
        absl::StrCat("textures: the frames [", first_frame, ", ", last_frame, ") hold none"));
  }
  for (const std::string& id : cameras) {
    if (id.empty()) return absl::InvalidArgumentError("textures: an empty camera id");
  }
  return options.Validate();
}

absl::StatusOr<JobResult> RunTextures(const TexturesJob& job, const std::function<void(const JobProgress&)>& progress,
                                      const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  const std::string fit = PathInTake(job.take_dir, job.fit_dir, "derived/fit");
  const std::string maps = PathInTake(job.take_dir, job.photometric_dir, "derived/photometric");
  if (!fs::is_directory(fit)) return absl::NotFoundError(absl::StrCat(fit, ": no fit (run the fit stage first)"));
  if (!fs::is_directory(maps)) {
    return absl::NotFoundError(absl::StrCat(maps, ": no photometric maps (run the photometric stage first)"));
  }
  STAGE_ASSIGN_OR_RETURN(const int64_t last, LastFrame(job, fit));
  const std::vector<std::string> cameras =
      job.cameras.empty() ? CamerasIn(FrameDir(maps, job.first_frame)) : job.cameras;
  if (cameras.empty()) {
    return absl::NotFoundError(absl::StrCat(FrameDir(maps, job.first_frame), ": no camera's photometric maps"));
  }
  STAGE_ASSIGN_OR_RETURN(const LoadedRig rig, LoadTakeRig(job.take_dir));
  STAGE_ASSIGN_OR_RETURN(const std::optional<CameraCalibration> calibration,
                         LoadJobCalibration(job.take_dir, job.calibration));
  JobResult result;
  result.output_dir = PathInTake(job.take_dir, job.output_dir, "derived/textures");
  JobProgress p{0, last - job.first_frame,
                absl::StrCat("texture fusion: ", last - job.first_frame, " frame(s) of ", cameras.size(), " view(s)")};
  if (progress) progress(p);
  for (int64_t frame = job.first_frame; frame < last; ++frame) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(
          absl::StrCat("texture fusion on ", job.take_dir, " cancelled after ", result.units, " frame(s)"));
    }
    STAGE_RETURN_IF_ERROR(
        FuseFrame(job, rig, calibration ? &*calibration : nullptr, fit, maps, cameras, frame, result.output_dir));
    ++result.units;
    p.done = result.units;
    p.message = absl::StrFormat("frame %d: %d views fused at %d x %d", frame, cameras.size(), job.options.size,
                                job.options.size);
    if (progress) progress(p);
  }
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/run.json", RunJson(job, cameras, last)));
  return result;
}

}  // namespace stage::processing
