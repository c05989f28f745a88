// What the asset's training sources share (asset_train.cc: the geometry VAE and the run's files; asset_drive.cc: the
// expression VAE, the mapping and the driven evaluation). Torch-free.
#pragma once

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

// The frames of each split, in take order.
std::vector<int64_t> FramesOf(const AssetDataset& d, SampleSplit split);

// A dataset's identity: FNV-1a of its description (source, take, sizes, sequences, split) and frame numbers.
std::string DatasetId(const AssetDataset& d);

// An NCHW map of `size` texels at `uv` (texel centres at (i + 0.5) / size, row 0 at v = 1), bilinear, clamped;
// nullopt where one of the four texels is not valid.
std::optional<Eigen::Vector3d> SampleNchw(const std::vector<float>& map, const std::vector<float>& valid, int size,
                                          const Eigen::Vector2f& uv);

// The error of `recovered` maps (frame -> NCHW map) of `frames` against the truth (SplitError).
SplitError Error(const NetMaps& m, const FaceTemplate& face, const std::vector<int64_t>& frames,
                 const std::function<std::vector<float>(int64_t)>& recovered);

// A finished run's trainer.json options, of a run of `network` ("geometry", "expression", "mapping"; NotFound naming
// the file where there is no run, InvalidArgument where it is another network's).
absl::StatusOr<nlohmann::json> RunOptions(const std::string& run_dir, const std::string& network);
// Integer options of `o` into `fields` (errors name the run's trainer.json and the option).
absl::Status ReadIntOptions(const std::string& run_dir, const nlohmann::json& o,
                            std::initializer_list<std::pair<const char*, int*>> fields);

// Finished runs' nets: their options from trainer.json, their weights (and normalizations) from the run's net file
// (geometry_vae.pt, expression_vae.pt, mapping.pt). The expression run's held-out cameras into `held_out`; the
// mapping's sizes are checked against `input` and `output`.
absl::StatusOr<std::unique_ptr<GeometryVae>> LoadGeometryNet(const std::string& run_dir, int threads);
absl::StatusOr<std::unique_ptr<ExpressionVae>> LoadExpressionNet(const std::string& run_dir, int threads,
                                                                 std::vector<std::string>* held_out);
absl::StatusOr<std::unique_ptr<LatentMapping>> LoadMappingNet(const std::string& run_dir, int input, int output,
                                                              int threads);

// A finished geometry run's net with `data`, the dataset prepared at the net's input size.
absl::StatusOr<std::unique_ptr<GeometryVae>> LoadGeometryRun(const std::string& run_dir, const std::string& dataset,
                                                             PreparedData* data, int threads = 0);

// A run directory: `dir`, or beside the dataset under `name`.
std::string RunDir(const std::string& dir, const std::string& dataset, const char* name);

// A crop of `size` pixels across (8 bits) averaged down to `input` pixels across (size a multiple of it), 0..1, into
// `out` (input^2 values): what the expression VAE sees of a dataset's crop or of a new image's.
void CropToNetInput(const uint8_t* crop, int size, int input, float* out);

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
