// What the asset's training sources share (asset_train.cc: the geometry VAE and the run's files; asset_drive.cc: the
// expression VAE, the mapping and the driven evaluation). Torch-free.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <initializer_list>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/asset_net.h"
#include "stage/processing/asset_train.h"
#include "stage/processing/face_template.h"
#include "stage/processing/photometric.h"
#include "training_run.h"

namespace stage::processing::asset_internal {

// The dataset's maps at the net's resolution, NCHW (3 x S x S each), with their validity (S x S each).
struct NetMaps {
  int size = 0;
  std::vector<std::vector<float>> maps, valid;
};

// A dataset read for a geometry net of input `size`: its maps at that size, the training frames, their mean and
// spread (mm).
struct PreparedData {
  AssetDataset dataset;
  NetMaps maps;
  std::vector<int64_t> train;
  std::vector<float> mean;
  float scale = 0;
};
absl::StatusOr<PreparedData> Prepare(const std::string& path, int size);

// A frame's textures (in x in x kTextureChannels, and their validity) at the net's `size` (in a multiple of it),
// averaged down, a texel valid where any of its sources is: C x S x S and S x S (1 or 0).
void DownsampleTextureMap(const float* maps, const uint8_t* valid, int in, int size, std::vector<float>* out,
                          std::vector<float>* out_valid);

// The neutral frame's textures at full resolution (the dataset's neutral_textures) and at the texture VAE's size.
struct NeutralTextures {
  Image albedo;  // RGBA, linear; alpha 1 where the skin's textures are
  Image specular, normal;
  int net_size = 0;
  std::vector<float> net, net_valid;  // C x S x S and S x S: the dataset's first frame at the net's size
};
// Errors name the files: missing, or not of the size the dataset says.
absl::StatusOr<NeutralTextures> LoadNeutralTextures(const AssetDataset& d, int net_size);

// A frame's textures as images: linear albedo (RGB), specular intensity, unit tangent-space normals.
struct TextureImages {
  Image albedo, specular, normal;
};
// The decoded textures (C x S x S) as they are, at the net's size.
TextureImages NetTextureImages(const std::vector<float>& decoded, int size);
// The decoded textures at the neutral textures' full resolution: the wrinkle maps (decoded less the neutral frame's
// at the net's size, where both hold the skin; 0 elsewhere) upsampled bilinearly and added to the neutral textures.
// Albedo and specular >= 0, normals unit; texels the neutral textures do not hold are 0.
TextureImages ApplyWrinkleMaps(const NeutralTextures& neutral, const std::vector<float>& decoded);

// The frames of each split, in take order.
std::vector<int64_t> FramesOf(const AssetDataset& d, SampleSplit split);

// A dataset's identity: FNV-1a of its description (source, take, sizes, sequences, split) and frame numbers.
std::string DatasetId(const AssetDataset& d);

// An NCHW map of `size` texels at `uv` (texel centres at (i + 0.5) / size, row 0 at v = 1), bilinear, clamped;
// nullopt where one of the four texels is not valid.
std::optional<Eigen::Vector3d> SampleNchw(const std::vector<float>& map, const std::vector<float>& valid, int size,
                                          const Eigen::Vector2f& uv);

// Each texel's weight in the geometry VAE's map losses at `size` (before validity), S x S: `weight` on the texels a
// kEye or kMouth vertex of `face` samples (SampleNchw's four) and the ring about them, 1 elsewhere. Empty when
// `weight` is 1 (AssetTrainJob::region_weight).
std::vector<float> RegionWeights(const FaceTemplate& face, int size, double weight);

// The error of `recovered` maps (frame -> NCHW map) of `frames` against the truth (SplitError).
SplitError Error(const NetMaps& m, const FaceTemplate& face, const std::vector<int64_t>& frames,
                 const std::function<std::vector<float>(int64_t)>& recovered);

// PCA of the training maps (`train` of m.maps) about `mean`: at most k components, the columns of the result
// (orthonormal), from the frames' Gram matrix; none of the data's null space.
Eigen::MatrixXf Pca(const NetMaps& m, const std::vector<int64_t>& train, const std::vector<float>& mean, int k);

// A finished run's trainer.json options, of a run of `network` ("geometry", "expression", "mapping"; NotFound naming
// the file where there is no run, InvalidArgument where it is another network's).
absl::StatusOr<nlohmann::json> RunOptions(const std::string& run_dir, const std::string& network);
// Integer options of `o` into `fields` (errors name the run's trainer.json and the option).
absl::Status ReadIntOptions(const std::string& run_dir, const nlohmann::json& o,
                            std::initializer_list<std::pair<const char*, int*>> fields);

// Finished runs' nets: their options from trainer.json, their weights (and normalizations) from the run's net file
// (geometry_vae.pt, expression_vae.pt, mapping.pt). The expression run's held-out cameras into `held_out`; the
// mapping's sizes are checked against `input` and `output`; `network`: the mapping's ("mapping") or the texture
// mapping's ("texture_mapping"), its net in <network>.pt.
absl::StatusOr<std::unique_ptr<GeometryVae>> LoadGeometryNet(const std::string& run_dir, int threads);
absl::StatusOr<std::unique_ptr<ExpressionVae>> LoadExpressionNet(const std::string& run_dir, int threads,
                                                                 std::vector<std::string>* held_out);
absl::StatusOr<std::unique_ptr<LatentMapping>> LoadMappingNet(const std::string& run_dir, int input, int output,
                                                              int threads, const std::string& network = "mapping");

// A finished texture run's net (texture_vae.pt); a finished texture mapping run's net, refused (FailedPrecondition
// naming the run) unless trained from the geometry and texture runs given as they are now.
absl::StatusOr<std::unique_ptr<TextureVae>> LoadTextureNet(const std::string& run_dir, int threads);
absl::StatusOr<std::unique_ptr<LatentMapping>> LoadTextureMappingNet(const std::string& run_dir,
                                                                     const std::string& geometry_run,
                                                                     const std::string& texture_run,
                                                                     int geometry_latent, int texture_latent,
                                                                     int threads);

// A finished geometry run's net with `data`, the dataset prepared at the net's input size.
absl::StatusOr<std::unique_ptr<GeometryVae>> LoadGeometryRun(const std::string& run_dir, const std::string& dataset,
                                                             PreparedData* data, int threads = 0);

// A run directory: `dir`, or beside the dataset under `name`.
std::string RunDir(const std::string& dir, const std::string& dataset, const char* name);
// A run a later run was trained from: `dir` where given; else the `name` run `later`'s trainer.json records it was
// trained from ("<name>_run") where that directory still holds that very run (its identity, "<name>_run_id", as
// recorded); else beside the dataset (RunDir: a tree moved or copied whole). `later` may be empty (none). The run
// taken is checked after (CheckTrainedFrom), as one given is.
std::string RunTrainedFrom(const std::string& dir, const std::string& later, const char* name,
                           const std::string& dataset);
// The runs a driven asset loads: each as given, else as the fine-tuning's run (`finetune`, resolved: "" for none)
// records it, or where there is no fine-tuning's run as the mapping's run records its VAEs, else beside the dataset
// (RunTrainedFrom).
struct DrivenRuns {
  std::string geometry, expression, mapping;
};
DrivenRuns ResolveDrivenRuns(const std::string& dataset, const std::string& geometry_run,
                             const std::string& expression_run, const std::string& mapping_run,
                             const std::string& finetune);

// A crop of `size` pixels across (8 bits) averaged down to `input` pixels across (size a multiple of it), 0..1, into
// `out` (input^2 values): what the expression VAE sees of a dataset's crop or of a new image's.
void CropToNetInput(const uint8_t* crop, int size, int input, float* out);

// The dataset's crops at a net's input size (each averaged down from the dataset's), 0..1.
struct Crops {
  int size = 0, cameras = 0;
  std::vector<float> pixels;  // frames x cameras x size^2
  size_t Pixels() const { return static_cast<size_t>(size) * size; }
  const float* At(int64_t frame, int camera) const {
    return pixels.data() + (static_cast<size_t>(frame) * cameras + camera) * Pixels();
  }
};

absl::StatusOr<Crops> CropsAt(const AssetDataset& d, int size);
bool ImageValid(const AssetDataset& d, int64_t frame, int camera);
// The dataset's cameras that are not held out (indices), checking the held-out names.
absl::StatusOr<std::vector<int>> TrainedCameras(const AssetDataset& d, const std::vector<std::string>& held_out);

// The three finished nets and what they read: the asset as the driven evaluation and inference use it.
struct DrivenAsset {
  PreparedData data;  // at the geometry net's size
  std::unique_ptr<GeometryVae> geometry;
  std::unique_ptr<ExpressionVae> expression;
  std::unique_ptr<LatentMapping> mapping;  // null until trained or loaded
  std::unique_ptr<DrivingNet> driver;      // the fine-tuned driving path, where one is trained or loaded
  std::vector<std::string> held_out;
  std::vector<int> trained;
  Crops crops;
  std::vector<float> expression_latents;  // every crop's (EncodeAll), where the mapping's training needs them
  std::vector<float> geometry_latents;    // every frame's map's geometry latent's mean
  std::vector<float> driven;              // every crop's geometry latent as driven (Drive), frames x cameras rows

  int ExpressionSize() const { return expression->options().expression_latent; }
  int GeometrySize() const { return geometry->options().geometry_latent; }
  std::vector<float> DrivenOf(int64_t frame, int camera) const {
    const size_t row = static_cast<size_t>(frame) * crops.cameras + camera;
    return {driven.begin() + static_cast<std::ptrdiff_t>(row * GeometrySize()),
            driven.begin() + static_cast<std::ptrdiff_t>((row + 1) * GeometrySize())};
  }
  std::vector<float> ExpressionOf(int64_t frame, int camera) const {
    const size_t row = static_cast<size_t>(frame) * crops.cameras + camera;
    const size_t width = ExpressionSize() + expression->options().view_latent;
    return {expression_latents.begin() + static_cast<std::ptrdiff_t>(row * width),
            expression_latents.begin() + static_cast<std::ptrdiff_t>(row * width + ExpressionSize())};
  }
};

// The geometry VAE's and expression VAE's finished runs on `dataset`: the crops at the expression VAE's size and
// every frame's map's geometry latent.
absl::StatusOr<DrivenAsset> LoadDrivenAsset(const std::string& dataset, const std::string& geometry_run,
                                            const std::string& expression_run, int threads);
// The finished runs (empty names: beside the dataset) loaded and driven from every crop (Drive): through the
// fine-tuned path of `finetune_run` (a run's directory), or through the mapping where it is empty.
absl::StatusOr<DrivenAsset> LoadDriven(const std::string& dataset, const std::string& geometry_run,
                                       const std::string& expression_run, const std::string& mapping_run,
                                       const std::string& finetune_run, int threads);
// `a.driven`: every crop's geometry latent through the fine-tuned driver where there is one, else through the
// expression VAE's encoder and the mapping.
absl::Status Drive(DrivenAsset* a);
// A finished fine-tuning run's driving net (FineTuneDrivingAsset's) over the nets of the expression and mapping runs
// given; the geometry, expression and mapping runs must be those it was fine-tuned from (FailedPrecondition naming
// the run otherwise: its output is the geometry VAE's latent, which another geometry run decodes wrongly).
absl::StatusOr<std::unique_ptr<DrivingNet>> LoadDrivingNet(const std::string& run_dir, const std::string& geometry_run,
                                                           const std::string& expression_run,
                                                           const std::string& mapping_run,
                                                           const ExpressionVae& expression,
                                                           const LatentMapping& mapping, int threads);
// The fine-tuning run inference and evaluation use: `run`; where it is empty, DATASET's directory/finetune if it holds
// a run's net (driving_net.pt, written at a run's end), else none (""); and none where `run` is "none". A run started
// again and stopped part way is refused by LoadDrivingNet, not passed over.
std::string FineTuneRun(const std::string& run, const std::string& dataset);
// The paper's protocol on `a.driven` (DrivenEvaluation).
absl::StatusOr<DrivenEvaluation> EvaluateDriven(const DrivenAsset& a);
// A driven net's training (the mapping's, the fine-tuning's: `loop` with one loss) run to its end into `result` (its
// steps, resume and losses; `progress` after every step), the net saved as the run's `net_file`, then `a` driven
// (Drive), evaluated (evaluation.json) and drawn (driven.png).
absl::Status RunDrivenTraining(internal::TrainingLoop loop,
                               const std::function<bool(int64_t, int64_t, double)>& progress,
                               const std::string& net_file, DrivenAsset* a, MappingTrainResult* result);
// The picture (WriteDrivenPicture) of the middle frame of the held-out blocks (of the training frames where none is
// held out), driven from the first held-out camera that recorded it (a trained one where none is held out).
absl::Status WritePicture(const DrivenAsset& a, const std::string& path);
// The mapping's training pairs: (frame, camera) of training frames by trained cameras that recorded them.
std::vector<std::pair<int64_t, int>> MappingPairs(const DrivenAsset& a);
// Per dimension: the mean and the spread (standard deviation, at least 1e-6) of `rows` of `width` values.
void MeanAndSpread(const std::vector<std::vector<float>>& rows, int width, std::vector<float>* mean,
                   std::vector<float>* spread);
// Into a run's options `j`: each named run's directory ("<name>_run") and identity ("<name>_run_id", RunId).
absl::Status AddRunIdentities(std::initializer_list<std::pair<const char*, std::string>> runs, nlohmann::json* j);
// FailedPrecondition naming `run_dir` unless its options `o` hold the named runs' identities as they are now (the run
// was `trained` from them, not from runs trained again since).
absl::Status CheckTrainedFrom(const std::string& run_dir, const nlohmann::json& o, const char* trained,
                              std::initializer_list<std::pair<const char*, std::string>> runs);
// A finished run's identity: a hash of its trainer.json (its options, its last step and generator state), so that a
// later stage is not resumed over runs trained again since.
absl::StatusOr<std::string> RunId(const std::string& run_dir);

// One frame of the asset driven from one camera, drawn (docs/asset.md's picture): the camera's crop, the frame's
// truth and the driven mesh seen from the front, and the driven mesh's distance to the truth per vertex in colour.
struct DrivenPicture {
  std::string title, camera_label;
  const uint8_t* crop = nullptr;  // 8-bit grey, crop_size^2
  int crop_size = 0;
  std::vector<float> truth, valid, driven;  // NCHW maps at `size` (head frame, mm), the truth's validity
  int size = 0;
  const FaceTemplate* face = nullptr;
};
absl::Status WriteDrivenPicture(const std::string& path, const DrivenPicture& p);

// A split's error as JSON (the evaluations' files).
nlohmann::json SplitJson(const SplitError& x);

// The schedule's options as a resume must find them.
void AddScheduleJson(const TrainingSchedule& s, nlohmann::json* j);

}  // namespace stage::processing::asset_internal
