// A neural asset's dataset (docs/asset.md#the-dataset): a take's frames turned into training samples, each the
// frame's UV geometry map in the face template's layout (head frame, mm; the head's pose kept apart), with a
// held-out split as the FaStage paper's: 20 % of the frames in contiguous blocks, and one whole expression sequence
// never seen in training. The geometry comes from the reconstruction (the template fit's geometry maps) or from the
// simulator's truth (its UV position maps resampled into the template's layout), chosen by `source`, so the asset
// can be built before reconstruction is perfect. Written as one array file (stage/storage/array_file.h: HDF5, which
// h5py reads):
//   frame            int64 (N)                the take's frame
//   split            uint8 (N)                SampleSplit
//   sequence         int32 (N)                index into the description's `sequences`, -1 where none is named
//   geometry         float32 (N, S, S, 3)     head frame, mm; 0 where not valid
//   valid            uint8 (N, S, S)          1 where the texel holds the surface's point
//   stage_from_head  float32 (N, 4, 4)        the head's pose
//   images           uint8 (N, V, I, I)       each machine-vision camera's full-lit frame cropped about the face
//                                             (grey, gamma 2.2 over the camera's white); only when the take has them
//   image_valid      uint8 (N, V)             1 where the camera recorded the frame's full-lit slot
//   textures         float32 (N, T, T, 7)     the skin's textures in the template's layout: linear albedo RGB,
//                                             specular intensity, the tangent-space normal (x along +u, y along +v,
//                                             z out); 0 where not valid. Only when the source has them
//   texture_valid    uint8 (N, T, T)          1 where the texel holds the skin's textures
//   attributes: format ("fastage-asset-dataset-1"), description (JSON: source, take, size, sequences, the split, the
//   cameras and their crops), neutral_textures (JSON: the full-resolution neutral textures' texels across, where
//   they were written, in the directory beside the file named for it, DATASET-neutral/; apart from the description,
//   which is the dataset's identity for training).
//
// The crops are fixed per camera, as a stage's cameras are: a square of `crop_mm` at the face's place when the head
// is at rest (the face template's centre at the stage's origin pose), wherever the head then moves, so that a new
// image of the same camera is cropped the same way with no pose known.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace stage::processing {

// Where a dataset's geometry and textures come from.
enum class AssetSource {
  // The simulator's ground truth (TAKE/ground_truth/frame-NNNNNN/uv_position.exr, pose.json; the textures from
  // uv_albedo.exr, uv_material.exr and uv_normal.exr, which stage-sim-render writes with --uv-textures).
  kTruth,
  // The template fit (TAKE/derived/fit/frame-NNNNNN/geometry_map.exr, pose.json) and texture fusion
  // (TAKE/derived/textures/frame-NNNNNN/).
  kReconstruction,
};

// The channels of a dataset's textures: albedo R, G, B (linear), specular intensity, tangent-space normal x, y, z.
inline constexpr int kTextureChannels = 7;
const char* AssetSourceName(AssetSource source);  // "truth", "reconstruction"
absl::StatusOr<AssetSource> ParseAssetSource(const std::string& name);

enum class SampleSplit : uint8_t {
  kTrain = 0,
  kHeldOutBlock = 1,     // in one of the held-out contiguous blocks
  kHeldOutSequence = 2,  // in the held-out expression sequence
};
const char* SampleSplitName(SampleSplit split);  // "train", "held_out_block", "held_out_sequence"

struct DatasetOptions {
  std::string take_dir;
  // The dataset file; empty: TAKE/derived/asset/dataset.h5.
  std::string output;
  AssetSource source = AssetSource::kTruth;
  // Frames [first_frame, last_frame) that the source holds; last_frame < 0: all from first_frame.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // Every frame_step-th of the frames the source holds in that range, from the first (1..1000).
  int frame_step = 1;
  // Texels across the geometry map (16..1024).
  int geometry_size = 256;
  // The share of the frames (without the held-out sequence) held out, as `held_out_blocks` contiguous blocks spread
  // evenly over the take (0 to 0.5; 1 to 64 blocks).
  double held_out_fraction = 0.2;
  int held_out_blocks = 5;
  // The expression sequence held out whole (a name the simulator's pose files give, "smile-3"); empty: the last one
  // the frames hold whole (none if the take names fewer than three); "none": none.
  std::string held_out_sequence;
  // The machine-vision cameras whose full-lit frames are cropped (ids; empty: every machine-vision camera the take
  // has a frame file of; none recorded: no images). `calibration` places them (a file, or a directory holding
  // cameras.json, relative to the take or absolute; empty: the rig's nominal models).
  std::vector<std::string> cameras;
  std::string calibration;
  // Texels across the textures (16..1024), taken where the source has them for the first frame (then every frame
  // must); 0: none.
  int texture_size = 128;
  // The neutral frame's (the first frame's) textures at full resolution, written beside the dataset (its file's name
  // less .h5, plus "-neutral/": albedo.exr with validity as alpha, specular.exr, normal_tangent.exr, in the
  // template's layout as the dataset's): inference adds the driven wrinkle maps to them. Texels across (16..8192); 0:
  // the source's own (the truth's UV maps', texture fusion's textures'); -1: none. Only with textures.
  int neutral_texture_size = 0;
  // Texels across a crop (16..512), and the crop's side at the face, mm (50..1000).
  int image_size = 128;
  double crop_mm = 280;
  // Called after each frame: (done, total); and asked before each: true stops the build (Cancelled, nothing
  // written).
  std::function<void(int64_t, int64_t)> progress;
  std::function<bool()> cancelled;

  absl::Status Validate() const;
};

struct DatasetSummary {
  std::string path;
  AssetSource source = AssetSource::kTruth;
  int geometry_size = 0;
  int64_t frames = 0, train = 0, held_out_block = 0, held_out_sequence = 0;
  std::string sequence;  // held out; empty when none
  std::vector<std::string> sequences;
  std::vector<std::string> cameras;  // whose crops the dataset holds
  int image_size = 0;
  // Texels across the textures; 0: none, and `textures_note` says why.
  int texture_size = 0;
  std::string textures_note;
  // The neutral frame's full-resolution textures: their directory and texels across (0: none).
  std::string neutral_textures_dir;
  int neutral_texture_size = 0;
  // Over the frames' valid texels: the mean count per frame, and how far the geometry moves from the dataset's mean
  // (RMS, mm): what a model of it has to explain.
  double valid_texels = 0, rms_from_mean_mm = 0;
};

// Builds the dataset (see above). Errors name the take and what is missing: no frames from the source, a frame's
// file, a sequence not in the take, a geometry map of another layout.
absl::StatusOr<DatasetSummary> BuildAssetDataset(const DatasetOptions& options);

// How the dataset crops a camera's frames (its description's "crops"): the square's centre and side in the camera's
// pixels, and the white its crops are scaled to (DN over the black level; 0 where the camera recorded no frame).
struct CropBox {
  std::string camera;
  double centre_x = 0, centre_y = 0, side = 0, white = 0;
};

// A dataset read back whole.
struct AssetDataset {
  std::string path;
  int geometry_size = 0;
  std::vector<int64_t> frame;
  std::vector<SampleSplit> split;
  std::vector<int32_t> sequence;
  std::vector<std::string> sequences;
  std::vector<float> geometry;         // frames x size x size x 3
  std::vector<uint8_t> valid;          // frames x size x size
  std::vector<float> stage_from_head;  // frames x 16, row-major
  std::vector<std::string> cameras;    // of the images (empty: none)
  int image_size = 0;
  std::vector<uint8_t> images;       // frames x cameras x image_size^2
  std::vector<uint8_t> image_valid;  // frames x cameras
  std::vector<CropBox> crops;        // per camera (empty in a dataset written before they were kept)
  int texture_size = 0;              // 0: no textures
  std::vector<float> textures;       // frames x texture_size^2 x kTextureChannels
  std::vector<uint8_t> texture_valid;  // frames x texture_size^2
  // The neutral frame's full-resolution textures (DatasetOptions::neutral_texture_size): their directory (absolute
  // or relative to the working directory) and texels across; empty and 0 where the dataset has none.
  std::string neutral_textures_dir;
  int neutral_texture_size = 0;
  std::string description;           // the JSON attribute
  int64_t frames() const { return static_cast<int64_t>(frame.size()); }
};
// Errors name the file: not a dataset, arrays of disagreeing lengths.
absl::StatusOr<AssetDataset> ReadAssetDataset(const std::string& path);
// The description alone (sizes, sequences, cameras and crops; no arrays read).
absl::StatusOr<AssetDataset> ReadAssetDatasetDescription(const std::string& path);

// The textures of the dataset's frame at index `i` (texture_size^2 x kTextureChannels, and their validity) read alone
// from its file (`d` from ReadAssetDatasetDescription is enough). Errors name the file.
absl::Status ReadDatasetFrameTextures(const AssetDataset& d, int64_t i, std::vector<float>* maps,
                                      std::vector<uint8_t>* valid);

// The crop box of `camera` in `d` (errors name the dataset, and the cameras it cropped).
absl::StatusOr<CropBox> DatasetCropBox(const AssetDataset& d, const std::string& camera);
// A grey frame (width x height floats, row-major) cropped as the dataset crops: the box's square averaged down to
// size x size pixels, over `white`, through a 1/gamma curve (2.2 for a camera's linear frames, as the dataset's
// crops; 1 for display-referred frames), 8 bits.
std::vector<uint8_t> CropFrame(const float* grey, int width, int height, const CropBox& box, int size, double white,
                               double gamma);
// The 99.5th percentile of the box's square in a grey frame (at least 1).
double CropWhite(const float* grey, int width, int height, const CropBox& box);
// The full-lit frames [first, last) (last < 0: to the end) of the box's camera in a take, cropped as the dataset
// cropped its own (black level removed, demosaiced to grey, the box's white, gamma 2.2): fn(frame, crop).
absl::Status ForEachTakeCrop(const std::string& take_dir, const CropBox& box, int size, int64_t first, int64_t last,
                             const std::function<absl::Status(int64_t, const std::vector<uint8_t>&)>& fn);

// The split of `frames` frames (in take order) whose sequence ids are `sequence` (-1: none), holding out sequence
// `held_out` (-1: none) and `fraction` of the rest in `blocks` even blocks. Exposed for tests.
std::vector<SampleSplit> SplitFrames(const std::vector<int32_t>& sequence, int32_t held_out, double fraction,
                                     int blocks);

}  // namespace stage::processing
