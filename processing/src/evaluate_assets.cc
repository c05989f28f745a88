// The UV assets against the simulator's ground truth (docs/assets.md#evaluation).
#include "stage/processing/evaluate_assets.h"

#include <algorithm>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/evaluate_mvs.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;

absl::StatusOr<nlohmann::json> ReadRun(const std::string& dir, const char* what) {
  const std::string path = dir + "/run.json";
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, what));
  nlohmann::json run = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (run.is_discarded() || !run.is_object()) return absl::DataLossError(absl::StrCat(path, ": not a JSON object"));
  return run;
}

bool Solved(const float* n) { return n[0] != 0 || n[1] != 0 || n[2] != 0; }

// The fit's run: its template, and the motion from its surfaces' frame to the truth's.
struct FitRun {
  FaceTemplate face;
  Eigen::Isometry3f to_truth = Eigen::Isometry3f::Identity();
};

absl::StatusOr<FitRun> LoadFitRun(const std::string& take, const std::string& fit, const std::string& truth,
                                  AssetsEvaluation* e) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json run, ReadRun(fit, "the fit's run record"));
  const std::string template_obj = run.value("template", "");
  FitRun r;
  auto face = template_obj.rfind("shipped", 0) == 0 ? ShippedFaceTemplate() : LoadFaceTemplate(template_obj);
  if (!face.ok()) return face.status();
  r.face = *std::move(face);
  e->fit_surface = run.value("surface", "mvs");
  const GeometrySpec surface = GeometrySpec::Parse(e->fit_surface);
  if (surface.source == GeometrySource::kMvs) {
    // Multi-view stereo's meshes are in its calibration's frame.
    STAGE_ASSIGN_OR_RETURN(const CameraCalibration true_cameras, ReadCameraCalibration(truth + "/cameras.json"));
    STAGE_ASSIGN_OR_RETURN(const TruthComparison in_truth, RunFrameToTruth(take, surface.Root(take), true_cameras));
    r.to_truth = in_truth.to_truth.cast<float>();
    e->frame_offset_mm = in_truth.frame_offset_mm;
    e->frame_rotation_deg = in_truth.frame_rotation_deg;
  }
  return r;
}

absl::Status EvaluateFitFrame(const FitRun& run, const std::string& fit, const std::string& truth, int64_t frame,
                              FrameAssetsEvaluation* out) {
  STAGE_ASSIGN_OR_RETURN(const TriangleMesh fitted, ReadObj(FrameDir(fit, frame) + "/mesh.obj"));
  STAGE_ASSIGN_OR_RETURN(const TriangleMesh true_mesh, ReadObj(FrameDir(truth, frame) + "/mesh.obj"));
  TemplateFit f;
  f.positions = fitted.positions;
  for (Eigen::Vector3f& p : f.positions) p = run.to_truth * p;
  auto evaluation = EvaluateFit(run.face, f, true_mesh);
  if (!evaluation.ok()) {
    return absl::Status(evaluation.status().code(),
                        absl::StrCat(FrameDir(fit, frame), ": ", evaluation.status().message()));
  }
  out->fit = *evaluation;
  out->has_fit = true;
  return absl::OkStatus();
}

// The textures' run: what they were fused from and how.
struct TexturesRun {
  LoadedRig rig;
  std::optional<CameraCalibration> calibration;
  std::vector<std::string> cameras;
  std::string fit, photometric;
  FusionOptions options;
};

absl::StatusOr<TexturesRun> LoadTexturesRun(const std::string& take, const std::string& textures) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json run, ReadRun(textures, "the texture fusion's run record"));
  const std::string path = textures + "/run.json";
  if (!run.contains("cameras") || !run.contains("options") || !run["options"].is_object()) {
    return absl::DataLossError(absl::StrCat(path, ": no cameras or options"));
  }
  TexturesRun r;
  STAGE_ASSIGN_OR_RETURN(r.rig, LoadTakeRig(take));
  const std::string calibration = run.value("calibration", "");
  if (calibration.rfind("the rig's nominal", 0) != 0) {
    STAGE_ASSIGN_OR_RETURN(r.calibration, LoadJobCalibration(take, calibration));
  }
  r.cameras = run["cameras"].get<std::vector<std::string>>();
  r.fit = PathInTake(take, run.value("fit", "derived/fit"));
  r.photometric = PathInTake(take, run.value("photometric", "derived/photometric"));
  const nlohmann::json& o = run["options"];
  FusionOptions& f = r.options;
  f.size = o.value("size", f.size);
  f.part = o.value("part", f.part);
  f.max_view_angle_deg = o.value("max_view_angle_deg", f.max_view_angle_deg);
  // A run written before the option existed fused lobes as far as the other maps.
  f.max_lobe_view_angle_deg = o.value("max_lobe_view_angle_deg", f.max_view_angle_deg);
  f.min_confidence = o.value("min_confidence", f.min_confidence);
  f.feather_px = o.value("feather_px", f.feather_px);
  f.occlusion_mm = o.value("occlusion_mm", f.occlusion_mm);
  f.contour_mm = o.value("contour_mm", f.contour_mm);
  f.dilation_px = o.value("dilation_px", f.dilation_px);
  if (auto s = f.Validate(); !s.ok()) return absl::DataLossError(absl::StrCat(path, ": ", s.message()));
  return r;
}

// The solve's view and the truth's of the same pixels with the same weights: both only where the truth's every ray
// meets the subject (its mask) and the solve has a normal; the truth's lobe only where the solve measured one.
absl::Status MaskedViews(const std::string& truth_dir, FusionView* solved, FusionView* truth) {
  const int w = solved->albedo.width, h = solved->albedo.height;
  truth->camera_id = solved->camera_id;
  truth->camera = solved->camera;
  truth->confidence = solved->confidence;
  Image mask, normal;
  struct File {
    const char* name;
    Image* image;
    int channels;
  };
  for (const File& f :
       {File{"mask.png", &mask, 1}, File{"normal_world.exr", &normal, 3}, File{"albedo.exr", &truth->albedo, 3},
        File{"specular.exr", &truth->specular, 1}, File{"roughness.exr", &truth->roughness, 1}}) {
    const std::string path = truth_dir + "/" + f.name;
    Image* image = f.image;
    const int channels = f.channels;
    STAGE_ASSIGN_OR_RETURN(*image, ReadImageFile(path));
    if (image->width != w || image->height != h || image->channels != channels) {
      return absl::InvalidArgumentError(absl::StrFormat("%s: %d x %d x %d, not the solve's %d x %d x %d", path,
                                                        image->width, image->height, image->channels, w, h, channels));
    }
  }
  truth->diffuse_normal = Image(w, h, 3);
  truth->specular_normal = Image(w, h, 3);
  const bool lobes = solved->specular_normal.width > 0;
  for (size_t i = 0; i < static_cast<size_t>(w) * h; ++i) {
    const float* n = &normal.pixels[3 * i];
    if (mask.pixels[i] > 0.99f && Solved(&solved->diffuse_normal.pixels[3 * i])) {
      std::copy_n(n, 3, &truth->diffuse_normal.pixels[3 * i]);
      if (!lobes || Solved(&solved->specular_normal.pixels[3 * i])) {
        std::copy_n(n, 3, &truth->specular_normal.pixels[3 * i]);
        continue;
      }
    } else {
      for (Image* image : {&solved->albedo, &solved->diffuse_normal, &solved->specular_normal}) {
        if (image->width > 0) std::fill_n(&image->pixels[i * 3], 3, 0.0f);
      }
    }
    for (Image* image : {&solved->specular, &solved->roughness, &truth->specular, &truth->roughness}) {
      if (image->width > 0) image->pixels[i] = 0;
    }
  }
  if (!lobes) truth->specular_normal = Image();
  return absl::OkStatus();
}

absl::Status EvaluateTexturesFrame(const TexturesRun& run, const std::string& textures, const std::string& truth,
                                   int64_t frame, FrameAssetsEvaluation* out) {
  STAGE_ASSIGN_OR_RETURN(const TriangleMesh mesh, ReadObj(FrameDir(run.fit, frame) + "/mesh.obj"));
  STAGE_ASSIGN_OR_RETURN(const Eigen::Isometry3f head_from_stage,
                         HeadFromStage(FrameDir(run.fit, frame) + "/pose.json"));
  std::vector<FusionView> solved, masked, truths;
  for (const std::string& id : run.cameras) {
    STAGE_ASSIGN_OR_RETURN(FusionView v, LoadFusionView(run.rig, run.calibration ? &*run.calibration : nullptr,
                                                        UnitDir(run.photometric, frame, id), id));
    solved.push_back(v);
    FusionView t;
    STAGE_RETURN_IF_ERROR(MaskedViews(UnitDir(truth, frame, id), &v, &t));
    masked.push_back(std::move(v));
    truths.push_back(std::move(t));
  }
  // The files are what fusion makes of the solve's maps.
  STAGE_ASSIGN_OR_RETURN(const FusedTextures again, FuseTextures(mesh, head_from_stage, solved, run.options));
  const std::string albedo_path = FrameDir(textures, frame) + "/albedo.exr";
  STAGE_ASSIGN_OR_RETURN(const Image on_disk, ReadImageFile(albedo_path));
  if (on_disk.pixels != again.albedo.pixels) {
    return absl::FailedPreconditionError(absl::StrCat(albedo_path, ": not what fusion makes of ", run.photometric,
                                                      " with its run's options (run textures again)"));
  }
  STAGE_ASSIGN_OR_RETURN(const FusedTextures mine, FuseTextures(mesh, head_from_stage, masked, run.options));
  STAGE_ASSIGN_OR_RETURN(const FusedTextures theirs, FuseTextures(mesh, head_from_stage, truths, run.options));
  STAGE_ASSIGN_OR_RETURN(out->textures, CompareTextures(mine, theirs));
  std::vector<bool> overlap(mine.views.size());
  for (size_t t = 0; t < overlap.size(); ++t) overlap[t] = mine.views[t] >= 2;
  STAGE_ASSIGN_OR_RETURN(out->textures_overlap, CompareTextures(mine, theirs, &overlap));
  out->has_textures = true;
  return absl::OkStatus();
}

}  // namespace

absl::Status AssetsEvaluateOptions::Validate() const {
  if (take_dir.empty()) return absl::InvalidArgumentError("evaluate assets: no take directory");
  if (!fit && !textures) return absl::InvalidArgumentError("evaluate assets: neither the fit nor the textures asked");
  if (first_frame < 0 || (last_frame >= 0 && last_frame <= first_frame)) {
    return absl::InvalidArgumentError(
        absl::StrCat("evaluate assets: the frames [", first_frame, ", ", last_frame, ") hold none"));
  }
  return absl::OkStatus();
}

absl::StatusOr<AssetsEvaluation> EvaluateAssets(const AssetsEvaluateOptions& o) {
  STAGE_RETURN_IF_ERROR(o.Validate());
  const std::string fit = PathInTake(o.take_dir, o.fit_dir, "derived/fit");
  const std::string textures = PathInTake(o.take_dir, o.textures_dir, "derived/textures");
  const std::string truth = PathInTake(o.take_dir, o.truth_dir, "ground_truth");
  const std::string results = o.textures ? textures : fit;
  int64_t last =
      o.last_frame >= 0 ? o.last_frame : EndOfFrames(results, o.textures ? "albedo.exr" : "mesh.obj", o.first_frame);
  if (last <= o.first_frame) {
    return absl::NotFoundError(absl::StrCat(results, ": no results from frame ", o.first_frame,
                                            o.textures ? " (run the textures stage first)" : " (run the fit first)"));
  }
  AssetsEvaluation e;
  std::optional<FitRun> fit_run;
  if (o.fit) {
    STAGE_ASSIGN_OR_RETURN(fit_run, LoadFitRun(o.take_dir, fit, truth, &e));
  }
  std::optional<TexturesRun> textures_run;
  if (o.textures) {
    STAGE_ASSIGN_OR_RETURN(textures_run, LoadTexturesRun(o.take_dir, textures));
  }
  for (int64_t frame = o.first_frame; frame < last; ++frame) {
    FrameAssetsEvaluation f;
    f.frame = frame;
    if (fit_run) STAGE_RETURN_IF_ERROR(EvaluateFitFrame(*fit_run, fit, truth, frame, &f));
    if (textures_run) STAGE_RETURN_IF_ERROR(EvaluateTexturesFrame(*textures_run, textures, truth, frame, &f));
    e.frames.push_back(std::move(f));
  }
  return e;
}

std::string FormatAssetsEvaluation(const AssetsEvaluation& e) {
  std::string out;
  bool fit = false, textures = false;
  for (const FrameAssetsEvaluation& f : e.frames) {
    fit |= f.has_fit;
    textures |= f.has_textures;
  }
  if (fit) {
    absl::StrAppendFormat(
        &out, "Template fit against the truth (surfaces: %s; moved %.2f mm, %.3f deg into the truth's frame)\n",
        e.fit_surface, e.frame_offset_mm, e.frame_rotation_deg);
    absl::StrAppend(&out,
                    "frame   region  vertices  rmse mm  p99 mm  to surface mm  sliding rmse mm  sliding p99 mm\n");
    for (const FrameAssetsEvaluation& f : e.frames) {
      if (!f.has_fit) continue;
      for (const auto& [name, r] : {std::pair{"skin", &f.fit.skin}, {"eyes", &f.fit.eyes}, {"mouth", &f.fit.mouth}}) {
        absl::StrAppendFormat(&out, "%5d  %7s  %8d  %7.2f  %6.2f  %13.2f  %15.2f  %14.2f\n", f.frame, name, r->vertices,
                              r->rmse_mm, r->p99_mm, r->surface_rmse_mm, r->sliding_rmse_mm, r->sliding_p99_mm);
      }
    }
  }
  if (textures) {
    if (fit) absl::StrAppend(&out, "\n");
    absl::StrAppend(
        &out,
        "Fused textures against the truth's maps fused with the same weights (all texels | seen by 2+ views)\n"
        "frame  texels            albedo %          diffuse deg      specular deg (median)  lobe texels\n");
    for (const FrameAssetsEvaluation& f : e.frames) {
      if (!f.has_textures) continue;
      const TextureErrors &a = f.textures, &b = f.textures_overlap;
      absl::StrAppendFormat(&out, "%5d  %7d | %7d  %5.2f | %5.2f   %5.2f | %5.2f   %5.2f (%4.2f) | %5.2f  %7d\n",
                            f.frame, a.texels, b.texels, 100 * a.albedo_mean, 100 * b.albedo_mean, a.normal_mean_deg,
                            b.normal_mean_deg, a.specular_normal_mean_deg, a.specular_normal_median_deg,
                            b.specular_normal_mean_deg, a.specular_texels);
    }
  }
  return out;
}

std::string AssetsEvaluationJson(const AssetsEvaluation& e) {
  auto fit_error = [](const FitError& r) {
    return nlohmann::ordered_json{{"vertices", r.vertices},
                                  {"rmse_mm", r.rmse_mm},
                                  {"p99_mm", r.p99_mm},
                                  {"surface_rmse_mm", r.surface_rmse_mm},
                                  {"sliding_rmse_mm", r.sliding_rmse_mm},
                                  {"sliding_p99_mm", r.sliding_p99_mm}};
  };
  auto texture_error = [](const TextureErrors& t) {
    return nlohmann::ordered_json{{"texels", t.texels},
                                  {"albedo_mean", t.albedo_mean},
                                  {"albedo_median", t.albedo_median},
                                  {"normal_mean_deg", t.normal_mean_deg},
                                  {"normal_median_deg", t.normal_median_deg},
                                  {"normal_p90_deg", t.normal_p90_deg},
                                  {"specular_texels", t.specular_texels},
                                  {"specular_normal_mean_deg", t.specular_normal_mean_deg},
                                  {"specular_normal_median_deg", t.specular_normal_median_deg},
                                  {"specular_median", t.specular_median},
                                  {"roughness_mean", t.roughness_mean}};
  };
  nlohmann::ordered_json j;
  j["fit_surface"] = e.fit_surface;
  j["frame_to_truth"] = {{"offset_mm", e.frame_offset_mm}, {"rotation_deg", e.frame_rotation_deg}};
  j["frames"] = nlohmann::ordered_json::array();
  for (const FrameAssetsEvaluation& f : e.frames) {
    nlohmann::ordered_json frame{{"frame", f.frame}};
    if (f.has_fit) {
      frame["fit"] = {
          {"skin", fit_error(f.fit.skin)}, {"eyes", fit_error(f.fit.eyes)}, {"mouth", fit_error(f.fit.mouth)}};
    }
    if (f.has_textures) {
      frame["textures"] = {{"all", texture_error(f.textures)},
                           {"seen_by_two_or_more", texture_error(f.textures_overlap)}};
    }
    j["frames"].push_back(std::move(frame));
  }
  return j.dump(2);
}

}  // namespace stage::processing
