// The trained asset driven from images: see asset_infer.h.
#include "stage/processing/asset_infer.h"

#include <algorithm>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "asset_train_internal.h"
#include "contact_sheet.h"
#include "stage/common/file_util.h"
#include "stage/common/mesh.h"
#include "stage/common/module.h"
#include "stage/common/status.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"
#include "stage/processing/mesh_sequence.h"
#include "stage/processing/photometric_stage.h"
#include "stage/processing/uv_geometry.h"
#include "video_reader.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;

// The three nets and what placing a frame's output needs.
struct Asset {
  std::unique_ptr<GeometryVae> geometry;
  std::unique_ptr<ExpressionVae> expression;
  std::unique_ptr<LatentMapping> mapping;
  // The driving path: the fine-tuned run's (driver_run), or the expression VAE's encoder and the mapping as trained.
  std::unique_ptr<DrivingNet> driver;
  std::string driver_run;
  // The textures' nets, where the asset drives its textures (texture_mapping_run).
  std::unique_ptr<TextureVae> texture;
  std::unique_ptr<LatentMapping> texture_mapping;
  std::string texture_mapping_run;
  // The neutral frame's full-resolution textures the wrinkle maps are added to, where the dataset keeps them.
  std::optional<asset_internal::NeutralTextures> neutral;
  FaceTemplate face;
  int image_size = 0;                 // the dataset's crops'
  std::vector<std::string> held_out;  // the cameras the expression VAE did not train on
};

// The runs' nets the options name (or those beside the dataset `d`), checked against its crops.
absl::StatusOr<Asset> LoadAsset(const AssetInferOptions& options, const AssetDataset& d) {
  using asset_internal::RunDir;
  Asset a;
  a.image_size = d.image_size;
  a.driver_run = asset_internal::FineTuneRun(options.finetune_run, options.dataset);
  const asset_internal::DrivenRuns runs = asset_internal::ResolveDrivenRuns(
      options.dataset, options.geometry_run, options.expression_run, options.mapping_run, a.driver_run);
  STAGE_ASSIGN_OR_RETURN(a.expression,
                         asset_internal::LoadExpressionNet(runs.expression, options.threads, &a.held_out));
  STAGE_ASSIGN_OR_RETURN(a.geometry, asset_internal::LoadGeometryNet(runs.geometry, options.threads));
  STAGE_ASSIGN_OR_RETURN(a.mapping,
                         asset_internal::LoadMappingNet(runs.mapping, a.expression->options().expression_latent,
                                                        a.geometry->options().geometry_latent, options.threads));
  if (!a.driver_run.empty()) {
    STAGE_ASSIGN_OR_RETURN(a.driver,
                           asset_internal::LoadDrivingNet(a.driver_run, runs.geometry, runs.expression, runs.mapping,
                                                          *a.expression, *a.mapping, options.threads));
  } else {
    STAGE_ASSIGN_OR_RETURN(
        a.driver, DrivingNet::Create(*a.expression, *a.mapping, {.train_encoder = false, .threads = options.threads}));
  }
  if (d.image_size % a.expression->options().input_size != 0) {
    return absl::FailedPreconditionError(absl::StrCat(options.dataset, ": its crops (", d.image_size,
                                                      " px) are not the expression VAE's input size's multiple"));
  }
  if (options.texture_mapping_run != "none") {
    const std::string run = RunDir(options.texture_mapping_run, options.dataset, "texture_mapping");
    if (!options.texture_mapping_run.empty() || fs::exists(run + "/texture_mapping.pt")) {
      const std::string texture_run =
          asset_internal::RunTrainedFrom(options.texture_run, run, "texture", options.dataset);
      STAGE_ASSIGN_OR_RETURN(a.texture, asset_internal::LoadTextureNet(texture_run, options.threads));
      STAGE_ASSIGN_OR_RETURN(
          a.texture_mapping,
          asset_internal::LoadTextureMappingNet(run, runs.geometry, texture_run, a.geometry->options().geometry_latent,
                                                a.texture->options().texture_latent, options.threads));
      a.texture_mapping_run = run;
      if (!d.neutral_textures_dir.empty()) {
        STAGE_ASSIGN_OR_RETURN(a.neutral, asset_internal::LoadNeutralTextures(d, a.texture->options().input_size));
      }
    }
  }
  STAGE_ASSIGN_OR_RETURN(a.face, ShippedFaceTemplate());
  return a;
}

// The textures of a geometry latent (the texture mapping, then the texture VAE's decoder) into `dir`: albedo.exr,
// specular.exr, normal_tangent.exr; at the neutral textures' full resolution where the asset has them, else at the
// net's.
absl::Status WriteDrivenTextures(const Asset& a, const std::vector<float>& geometry_latent, const std::string& dir) {
  STAGE_ASSIGN_OR_RETURN(const std::vector<float> latent, a.texture_mapping->Map(geometry_latent, 1));
  STAGE_ASSIGN_OR_RETURN(const std::vector<float> chw, a.texture->Decode(latent, 1));
  const asset_internal::TextureImages t = a.neutral
                                              ? asset_internal::ApplyWrinkleMaps(*a.neutral, chw)
                                              : asset_internal::NetTextureImages(chw, a.texture->options().input_size);
  STAGE_RETURN_IF_ERROR(WriteExr(dir + "/albedo.exr", t.albedo));
  STAGE_RETURN_IF_ERROR(WriteExr(dir + "/specular.exr", t.specular));
  return WriteExr(dir + "/normal_tangent.exr", t.normal);
}

// The output directory: the options', or the take's derived/asset/infer/<camera>, or <video's name>-asset beside it.
std::string OutputDir(const AssetInferOptions& options) {
  if (!options.output_dir.empty()) return options.output_dir;
  if (!options.take_dir.empty()) return options.take_dir + "/derived/asset/infer/" + options.camera;
  const fs::path video(options.video);
  return (video.parent_path() / (video.stem().string() + "-asset")).string();
}

// One frame's crop driven through the nets, its files written into `dir`; returns the template's vertices where the
// decoded map puts them.
absl::StatusOr<std::vector<Eigen::Vector3f>> DriveFrame(const Asset& a, const std::vector<uint8_t>& crop,
                                                        const std::string& dir, bool meshes) {
  const int input = a.expression->options().input_size;
  std::vector<float> net_input(static_cast<size_t>(input) * input);
  asset_internal::CropToNetInput(crop.data(), a.image_size, input, net_input.data());
  STAGE_ASSIGN_OR_RETURN(const std::vector<float> geometry_latent, a.driver->Drive(net_input, 1));
  STAGE_ASSIGN_OR_RETURN(const std::vector<float> nchw, a.geometry->Decode(geometry_latent, 1));
  const int s = a.geometry->options().input_size;
  const size_t texels = static_cast<size_t>(s) * s;
  GeometryMap map;
  map.size = s;
  map.points.resize(texels);
  map.state.assign(texels, TexelState::kCovered);
  for (size_t t = 0; t < texels; ++t) map.points[t] = {nchw[t], nchw[texels + t], nchw[2 * texels + t]};
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  const cv::Mat image(a.image_size, a.image_size, CV_8U, const_cast<uint8_t*>(crop.data()));
  if (!cv::imwrite(dir + "/crop.png", image))
    return absl::UnavailableError(absl::StrCat(dir, "/crop.png: cannot write"));
  STAGE_RETURN_IF_ERROR(WriteGeometryMap(dir + "/geometry_map.exr", map));
  if (a.texture_mapping != nullptr) STAGE_RETURN_IF_ERROR(WriteDrivenTextures(a, geometry_latent, dir));
  TriangleMesh mesh = a.face.mesh;
  for (size_t v = 0; v < mesh.positions.size(); ++v) {
    if (const auto p = SampleGeometryMap(map, mesh.uvs[v])) mesh.positions[v] = *p;
  }
  if (meshes) {
    STAGE_RETURN_IF_ERROR(
        WriteObj(dir + "/mesh.obj", mesh, "FaStage neural asset: the face template driven from one camera's image"));
  }
  return std::move(mesh.positions);
}

// The glTF material's textures: the neutral frame's full-resolution albedo in sRGB (black where it holds no skin:
// its albedo is zero there) and its tangent-space normals as (n + 1) / 2 (+z where none), as PNG files' bytes; none
// without them.
absl::StatusOr<MeshSequenceOptions> GltfTextures(const Asset& a, const AssetInferOptions& options) {
  MeshSequenceOptions o;
  if (!a.neutral || options.gltf_segment_frames == 0) return o;
  std::vector<uint8_t> bytes;
  if (!cv::imencode(".png", AlbedoPreview(a.neutral->albedo), bytes)) {
    return absl::InternalError("the glTF's base colour: PNG encoding failed");
  }
  o.base_color_png.assign(bytes.begin(), bytes.end());
  if (!cv::imencode(".png", NormalPreview(a.neutral->normal, /*empty=*/{255, 128, 128}), bytes)) {
    return absl::InternalError("the glTF's normal map: PNG encoding failed");
  }
  o.normal_png.assign(bytes.begin(), bytes.end());
  return o;
}

// The driven frames gathered into glTF binaries of `segment` frames each, `animation-<first frame>.glb`.
class GltfSegments {
 public:
  // `textures`: the material's (MeshSequenceOptions' base_color_png and normal_png; empty: none).
  GltfSegments(const AssetInferOptions& options, const TriangleMesh& rest, std::string dir,
               const MeshSequenceOptions& textures)
      : options_(options), rest_(rest), dir_(std::move(dir)), textures_(textures) {}

  absl::Status Add(int64_t frame, std::vector<Eigen::Vector3f> positions) {
    if (options_.gltf_segment_frames == 0) return absl::OkStatus();
    pending_.push_back({frame, std::move(positions)});
    if (static_cast<int>(pending_.size()) < options_.gltf_segment_frames) return absl::OkStatus();
    return Flush();
  }

  absl::Status Flush() {
    if (pending_.empty()) return absl::OkStatus();
    const std::string name = absl::StrFormat("animation-%06d.glb", pending_.front().frame);
    MeshSequenceOptions sequence = textures_;
    sequence.frames_per_second = options_.gltf_frames_per_second;
    sequence.generator = "FaStage neural asset, driven from camera " + options_.camera;
    STAGE_RETURN_IF_ERROR(WriteMeshSequenceGlb(dir_ + "/" + name, rest_, pending_, sequence));
    files_.push_back({{"file", name}, {"first_frame", pending_.front().frame}, {"frames", pending_.size()}});
    pending_.clear();
    return absl::OkStatus();
  }

  const nlohmann::json& files() const { return files_; }

 private:
  const AssetInferOptions& options_;
  const TriangleMesh& rest_;
  const std::string dir_;
  const MeshSequenceOptions textures_;
  std::vector<MeshSequenceFrame> pending_;
  nlohmann::json files_ = nlohmann::json::array();
};

// Each frame of a video (or image sequence) of the box's camera cropped as the dataset crops (display-referred
// frames: the first crop's white, no gamma).
absl::Status ForEachVideoCrop(const std::string& path, const CropBox& box, int size,
                              const std::function<absl::Status(int64_t, const std::vector<uint8_t>&)>& fn) {
  // The reader's module, opened the first time a video is read (video_reader.h).
  static const absl::StatusOr<internal::ReadVideoFn> read =
      OpenModuleAs<internal::ReadVideoFn>({.target = internal::kVideoReaderTarget,
                                           .entry = internal::kVideoReaderEntry,
                                           .what = "the video reader module"});
  if (!read.ok()) return read.status();
  double white = 0;
  return (*read)(path, [&](int64_t index, int width, int height, const float* pixels) -> absl::Status {
    const double half = box.side / 2;
    if (box.centre_x - half < 0 || box.centre_y - half < 0 || box.centre_x + half > width ||
        box.centre_y + half > height) {
      return absl::InvalidArgumentError(
          absl::StrFormat("%s: frames of %dx%d do not hold camera %s's crop box (%.0f px about %.0f, %.0f): are they "
                          "of that camera, at its resolution?",
                          path, width, height, box.camera, box.side, box.centre_x, box.centre_y));
    }
    if (white == 0) white = CropWhite(pixels, width, height, box);
    return fn(index, CropFrame(pixels, width, height, box, size, white, /*gamma=*/1));
  });
}

}  // namespace

absl::Status AssetInferOptions::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("asset inference: no dataset (the asset's)");
  if (camera.empty()) return absl::InvalidArgumentError("asset inference: no camera (whose images drive the asset)");
  if (take_dir.empty() == video.empty()) {
    return absl::InvalidArgumentError("asset inference: the images come from a take or a video, one of the two");
  }
  if (!video.empty() && (first_frame != 0 || last_frame >= 0)) {
    return absl::InvalidArgumentError("asset inference: frames are a take's: a video is read whole");
  }
  if (first_frame < 0 || (last_frame >= 0 && last_frame <= first_frame)) {
    return absl::InvalidArgumentError(absl::StrCat("asset inference: frames [", first_frame, ", ", last_frame, ")"));
  }
  if (threads < 0) return absl::InvalidArgumentError(absl::StrCat("asset inference: threads ", threads));
  if (gltf_segment_frames < 0) {
    return absl::InvalidArgumentError(absl::StrCat("asset inference: gltf_segment_frames ", gltf_segment_frames));
  }
  if (!(gltf_frames_per_second > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("asset inference: gltf_frames_per_second ", gltf_frames_per_second));
  }
  return absl::OkStatus();
}

absl::StatusOr<AssetInferResult> InferAsset(const AssetInferOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const AssetDataset d, ReadAssetDatasetDescription(options.dataset));
  STAGE_ASSIGN_OR_RETURN(const CropBox box, DatasetCropBox(d, options.camera));
  STAGE_ASSIGN_OR_RETURN(const Asset a, LoadAsset(options, d));
  AssetInferResult result;
  result.output_dir = OutputDir(options);
  STAGE_ASSIGN_OR_RETURN(const MeshSequenceOptions textures, GltfTextures(a, options));
  GltfSegments gltf(options, a.face.mesh, result.output_dir, textures);
  auto drive = [&](int64_t frame, const std::vector<uint8_t>& crop) -> absl::Status {
    if (options.cancelled && options.cancelled()) {
      return absl::CancelledError(absl::StrCat("asset inference stopped before frame ", frame, " (",
                                               result.frames.size(), " written into ", result.output_dir, ")"));
    }
    STAGE_ASSIGN_OR_RETURN(std::vector<Eigen::Vector3f> positions,
                           DriveFrame(a, crop, FrameDir(result.output_dir, frame), options.meshes));
    STAGE_RETURN_IF_ERROR(gltf.Add(frame, std::move(positions)));
    result.frames.push_back(frame);
    if (options.progress) options.progress(static_cast<int64_t>(result.frames.size()));
    return absl::OkStatus();
  };
  if (!options.take_dir.empty()) {
    STAGE_RETURN_IF_ERROR(
        ForEachTakeCrop(options.take_dir, box, d.image_size, options.first_frame, options.last_frame, drive));
  } else {
    STAGE_RETURN_IF_ERROR(ForEachVideoCrop(options.video, box, d.image_size, drive));
  }
  if (result.frames.empty()) {
    return absl::NotFoundError(absl::StrCat(options.take_dir.empty() ? options.video : options.take_dir,
                                            ": no frame of camera ", options.camera, " to drive the asset from"));
  }
  STAGE_RETURN_IF_ERROR(gltf.Flush());
  for (const auto& file : gltf.files()) result.gltf_files.push_back(file["file"].get<std::string>());
  result.textures = a.texture_mapping != nullptr;
  if (result.textures) result.texture_size = a.neutral ? a.neutral->albedo.width : a.texture->options().input_size;
  const nlohmann::json summary = {
      {"camera", options.camera},
      {"driven_through", a.driver_run.empty() ? "mapping" : "finetune"},
      {"finetune_run", a.driver_run},
      {"held_out", std::find(a.held_out.begin(), a.held_out.end(), options.camera) != a.held_out.end()},
      {"source", options.take_dir.empty() ? "video" : "take"},
      {"frames", result.frames},
      {"geometry_size", a.geometry->options().input_size},
      {"texture_mapping_run", a.texture_mapping_run},
      {"texture_size", result.texture_size},
      {"texture_net_size", a.texture == nullptr ? 0 : a.texture->options().input_size},
      {"textures_over", a.neutral ? "the neutral frame's textures at full resolution, plus the wrinkle maps"
                        : a.texture != nullptr ? "none: the decoded textures at the net's size"
                                               : ""},
      {"gltf", gltf.files()}};
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/frames.json", summary.dump(2) + "\n"));
  return result;
}

}  // namespace stage::processing
