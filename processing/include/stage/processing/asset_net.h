// The neural asset's networks (docs/asset.md), behind a torch-free interface: processing/src/asset_net.cc
// is the one translation unit that includes torch's headers for them. Callers hand in batches as plain arrays (NCHW
// floats, millimetres) with every random draw already made (the augmentation, the reparameterization's noise), so
// that the training's randomness is the caller's one generator: a run is the same for a seed and a thread count, and
// resumes from a checkpoint bit for bit.
//
// The geometry VAE (the FaStage paper's section 4.3): an encoder of a UV geometry map (3 channels, x y z in mm, and
// a validity channel) to a geometry latent and a pose latent; a decoder of the geometry latent to the map in the
// head's frame (canonical); a small MLP of the pose latent to a rotation (the 6D representation, Zhou et al. 2019)
// and a translation applied to the decoded map. Training shows it maps under random rigid motions (the caller's
// augmentation): the decoded map must be the unmoved one (the canonical loss), and the moved decoded map the moved
// input (the posed loss), so the geometry latent cannot hold the pose.
//
// One step of our own before the encoder: each input map is first aligned rigidly onto the training maps' mean
// (least squares over its valid texels, the Kabsch solution; no weights), and the pose MLP predicts the residual
// motion on top of that alignment undone. Without it the small nets this project trains on CPUs spent their capacity
// undoing the augmentation: on the unit test's made-up performance, held-out maps came back at 2.7 mm RMS after 300
// steps at +-5 degrees of augmentation (0.35 mm with none); aligned first, 0.43 mm at +-5 and 0.58 mm at +-15
// degrees (docs/asset.md#the-geometry-vae).
//
// Losses, over valid texels, in units of the dataset's spread (`scale`, mm):
//   canonical   mean |decode(z_geometry) - canonical|^2
//   posed       mean |R decode(z_geometry) + t - posed|^2 (the decoded map's gradient stopped: this term trains the
//               pose, the canonical term the geometry)
//   kl          the latents' KL divergence from N(0, I), summed over latent dimensions, mean over the batch
//   total       canonical + posed + kl_weight * kl
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace stage::processing {

namespace internal {  // the nets in the torch module (src/torch_nets.h)
class GeometryVaeNet;
class TextureVaeNet;
class ExpressionVaeNet;
class LatentMappingNet;
class DrivingNetNet;
}  // namespace internal

struct GeometryVaeOptions {
  // Texels across the maps the net sees (32..512, divisible by 2^levels). 64 by default: on two cores the chain at 64
  // trained long enough drives the asset closer than at 128 in a fraction of the time
  // (docs/asset.md#the-default-training).
  int input_size = 64;
  // Stride-2 levels of the encoder (and upsampling levels of the decoder), 2..7.
  int levels = 4;
  // Channels at full resolution, doubled at each level below up to max_channels (4..256).
  int base_channels = 8;
  int max_channels = 128;
  int geometry_latent = 32;  // 1..1024
  int pose_latent = 8;       // 1..64
  double kl_weight = 1e-4;   // >= 0
  // Threads for torch's loops (0: the cores this process may run on; SetTorchThreads).
  int threads = 0;
  uint64_t seed = 1;  // the weights' initialization
  absl::Status Validate() const;
};

// One training batch (B maps of input_size^2 texels; the caller's draws).
struct GeometryBatch {
  int batch = 0;
  std::vector<float> posed;      // B x 3 x S x S, mm: the input moved by the augmentation
  std::vector<float> canonical;  // B x 3 x S x S, mm: the input as it is (head frame)
  std::vector<float> valid;      // B x 1 x S x S, 1 or 0
  std::vector<float> noise;      // B x (geometry_latent + pose_latent): N(0, 1) draws for the reparameterization
  // B x 1 x S x S: each texel's weight in the maps' losses (0 where not valid); empty: the validity.
  std::vector<float> weight;
};

struct GeometryLosses {
  double total = 0, canonical = 0, posed = 0, kl = 0;
};

class GeometryVae {
 public:
  // A new net; `mean` (3 x S x S, mm: the training maps' mean) and `scale` (mm, > 0: their spread about it) are its
  // inputs' normalization, kept in its weights. Errors: options out of range, a mean of another size.
  static absl::StatusOr<std::unique_ptr<GeometryVae>> Create(const GeometryVaeOptions& options,
                                                             const std::vector<float>& mean, float scale);
  ~GeometryVae();
  GeometryVae(const GeometryVae&) = delete;
  GeometryVae& operator=(const GeometryVae&) = delete;

  // One Adam step at `learning_rate` on the batch. Errors: arrays of the wrong size.
  absl::StatusOr<GeometryLosses> TrainStep(const GeometryBatch& batch, double learning_rate);
  // The latents' means of `batch` maps (B x 3 x S x S, mm; valid B x S x S): B x (geometry_latent + pose_latent).
  absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& maps, const std::vector<float>& valid,
                                            int batch) const;
  // The canonical maps (B x 3 x S x S, mm) of `batch` geometry latents (B x geometry_latent).
  absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& geometry_latents, int batch) const;
  // The maps decoded and moved back where the inputs are (B x 3 x S x S, mm): the latents' means decoded, the pose
  // latent's residual motion and the alignment undone.
  absl::StatusOr<std::vector<float>> Reposed(const std::vector<float>& maps, const std::vector<float>& valid,
                                             int batch) const;

  // The weights and the optimizer's state (a torch archive). Load refuses a file of another net's shape
  // (FailedPrecondition, naming the file).
  absl::Status Save(const std::string& path) const;
  absl::Status Load(const std::string& path);

  // The net as TorchScript, which Python's torch.jit.load runs without this project's code: methods
  // encode(maps B x 3 x S x S mm, valid B x 1 x S x S) -> the latents' means (B x (geometry + pose), the alignment
  // included), decode(geometry latents) -> maps (mm), and forward = decode. Written atomically.
  absl::Status ExportTorchScript(const std::string& path) const;

  const GeometryVaeOptions& options() const;
  int64_t parameter_count() const;

 private:
  friend class DrivingNet;
  using Impl = internal::GeometryVaeNet;
  explicit GeometryVae(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The texture VAE (the FaStage paper's texture branch): an encoder of a frame's textures (`channels` of them: the
// dataset's albedo, specular intensity and tangent-space normal; and a validity channel) less the neutral textures,
// over their spread per channel, to a texture latent; a decoder of the latent to those wrinkle maps, which are added
// back to the neutral textures. The neutral textures and the per-channel spread are the net's normalization, kept in
// its weights. The trunks are the geometry VAE's. Losses over valid texels in units of the spread:
//   reconstruction   mean squared, over channels and texels
//   kl               the latent's KL divergence from N(0, I), summed over dimensions, mean over the batch
//   total            reconstruction + kl_weight kl
struct TextureVaeOptions {
  int input_size = 128;  // texels across (32..512, divisible by 2^levels)
  int levels = 5;        // 2..7
  int base_channels = 8;
  int max_channels = 128;
  int channels = 7;         // the textures' channels (1..16)
  int texture_latent = 32;  // 1..1024
  double kl_weight = 1e-4;  // >= 0
  int threads = 0;
  uint64_t seed = 1;
  absl::Status Validate() const;
};

struct TextureBatch {
  int batch = 0;
  std::vector<float> textures;  // B x C x S x S
  std::vector<float> valid;     // B x 1 x S x S, 1 or 0
  std::vector<float> noise;     // B x texture_latent: N(0, 1) draws
};

struct TextureLosses {
  double total = 0, reconstruction = 0, kl = 0;
};

class TextureVae {
 public:
  // `neutral` C x S x S, `scale` C values (> 0). Errors: options out of range, arrays of other sizes.
  static absl::StatusOr<std::unique_ptr<TextureVae>> Create(const TextureVaeOptions& options,
                                                            const std::vector<float>& neutral,
                                                            const std::vector<float>& scale);
  ~TextureVae();
  TextureVae(const TextureVae&) = delete;
  TextureVae& operator=(const TextureVae&) = delete;

  absl::StatusOr<TextureLosses> TrainStep(const TextureBatch& batch, double learning_rate);
  // The latent's means (B x texture_latent) of `batch` frames' textures (B x C x S x S) and validity (B x S x S).
  absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& textures, const std::vector<float>& valid,
                                            int batch) const;
  // The textures (B x C x S x S: the neutral ones plus the decoded wrinkle maps) of `batch` latents.
  absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& latents, int batch) const;
  absl::Status Save(const std::string& path) const;
  absl::Status Load(const std::string& path);
  // As TorchScript, which Python's torch.jit.load runs: encode(textures B x C x S x S, valid B x 1 x S x S) -> the
  // latent's means, decode(latents) -> textures, forward = decode. Written atomically.
  absl::Status ExportTorchScript(const std::string& path) const;
  const TextureVaeOptions& options() const;
  int64_t parameter_count() const;

 private:
  using Impl = internal::TextureVaeNet;
  explicit TextureVae(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The expression VAE (the FaStage paper's section 4.2): an encoder of one camera's crop about the face (grey, as the
// dataset holds it, 0..1) to an expression latent and a viewpoint latent, and a decoder of both (and the paper's
// indicator channel, zeros for the performer: the paper trains it with other people's images too) back to the crop.
// Trained on triplets that share an expression or a view: the anchor (frame a seen by camera i), the same frame seen
// by camera j, and another frame b seen by camera i. Losses (mean squared over pixels; latents sampled):
//   reconstruction   each of the three images from its own latents
//   expression swap  the anchor from the other view's expression latent and its own view latent (L_exp)
//   view swap        the anchor from its own expression latent and frame b's view latent (L_view)
//   cycle            frame b's expression with the other camera's view, decoded and encoded again, gives back the
//                    two latents (their means)
//   kl               the latents' KL divergence from N(0, I), summed over dimensions, mean over the batch
//   total            reconstruction + swap_weight (expression swap + view swap) + cycle_weight cycle + kl_weight kl
// The networks are the geometry VAE's trunks (3 x 3 convolutions, stride-2 levels, bilinear upsampling) on one grey
// channel. Trained on a dataset's crops by TrainExpressionAsset (asset_train.h).
struct ExpressionVaeOptions {
  int input_size = 64;  // pixels across a crop (32..512, divisible by 2^levels); 64 as the geometry VAE's
  int levels = 4;       // 2..7
  // Twice the geometry VAE's: the fine-tuned driving path's encoder is this one, and at 16 the held-out camera drove
  // the mouth as well in a quarter of the fine-tuning's steps as at 8
  // (docs/asset.md#the-rate-and-the-length-of-the-training).
  int base_channels = 16;
  int max_channels = 128;
  int expression_latent = 32;  // 1..1024
  int view_latent = 8;         // 1..64
  double kl_weight = 1e-4;
  double swap_weight = 1;
  // Off by default: at 0.1 the unit test's tiny net reconstructed 6x worse (mean squared 0.0018 against 0.0003
  // after 400 steps) and its latents stayed entangled; with only the encoder answering to it, the latents grew
  // without bound (KL 1300). The term is the paper's; a weight switches it on (at 0 it is not computed, and its
  // loss reads 0).
  double cycle_weight = 0;
  int threads = 0;
  uint64_t seed = 1;
  absl::Status Validate() const;
};

struct ExpressionBatch {
  int batch = 0;
  // B x 1 x I x I each, 0..1.
  std::vector<float> anchor, same_expression, same_view;
  // 3B x (expression_latent + view_latent): N(0, 1) draws, the anchors' B rows first, then the same expressions',
  // then the same views'.
  std::vector<float> noise;
};

struct ExpressionLosses {
  double total = 0, reconstruction = 0, expression_swap = 0, view_swap = 0, cycle = 0, kl = 0;
};

class ExpressionVae {
 public:
  static absl::StatusOr<std::unique_ptr<ExpressionVae>> Create(const ExpressionVaeOptions& options);
  ~ExpressionVae();
  ExpressionVae(const ExpressionVae&) = delete;
  ExpressionVae& operator=(const ExpressionVae&) = delete;

  absl::StatusOr<ExpressionLosses> TrainStep(const ExpressionBatch& batch, double learning_rate);
  // The latents' means of `batch` crops (B x 1 x I x I): B x (expression_latent + view_latent).
  absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& images, int batch) const;
  // The crops (B x 1 x I x I) of `batch` latents (B x (expression_latent + view_latent)).
  absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& latents, int batch) const;
  absl::Status Save(const std::string& path) const;
  absl::Status Load(const std::string& path);
  const ExpressionVaeOptions& options() const;
  int64_t parameter_count() const;

 private:
  friend class DrivingNet;
  using Impl = internal::ExpressionVaeNet;
  explicit ExpressionVae(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The mapping (the FaStage paper's section 4.4): an MLP from the expression latent (its mean, of one camera's crop) to
// the geometry latent (its mean, of the frame's map), trained with both VAEs frozen. Leaky ReLUs between `layers`
// linear layers of `hidden` units; the targets normalized per dimension (`target_mean`, `target_scale`, kept in the
// weights), the loss their mean squared error in those units. A dropout-free net this small needs its input noised to
// generalize from a few hundred frames: `input_noise` (the caller's draws, scaled) is added to the training inputs.
struct LatentMappingOptions {
  int input = 32;    // the expression latent's size (1..1024)
  int output = 32;   // the geometry latent's size (1..1024)
  int hidden = 256;  // 8..4096
  int layers = 3;    // linear layers, 2..8
  int threads = 0;
  uint64_t seed = 1;
  absl::Status Validate() const;
};

class LatentMapping {
 public:
  // Errors: options out of range, a mean or scale of another size, a scale not positive.
  static absl::StatusOr<std::unique_ptr<LatentMapping>> Create(const LatentMappingOptions& options,
                                                               const std::vector<float>& target_mean,
                                                               const std::vector<float>& target_scale);
  ~LatentMapping();
  LatentMapping(const LatentMapping&) = delete;
  LatentMapping& operator=(const LatentMapping&) = delete;

  // One Adam step on `batch` pairs (inputs B x input, targets B x output, noise B x input already scaled, added to
  // the inputs); the mean squared error in the targets' normalized units.
  absl::StatusOr<double> TrainStep(const std::vector<float>& inputs, const std::vector<float>& targets,
                                   const std::vector<float>& noise, int batch, double learning_rate);
  // Applied to images by DrivingNet (the expression VAE's encoder and the mapping as one net); to latents by Map (the
  // texture mapping's geometry latents): the targets (B x output, their own units) of `batch` inputs (B x input).
  absl::StatusOr<std::vector<float>> Map(const std::vector<float>& inputs, int batch) const;
  absl::Status Save(const std::string& path) const;
  absl::Status Load(const std::string& path);
  const LatentMappingOptions& options() const;
  int64_t parameter_count() const;

 private:
  friend class DrivingNet;
  using Impl = internal::LatentMappingNet;
  explicit LatentMapping(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The driving path fine-tuned (the third training stage, docs/asset.md#fine-tuning-the-driving-path): the expression
// VAE's encoder and the mapping as one net, image -> expression latent's mean -> mapping -> geometry latent, trained
// together on the frames' geometry latents (in the mapping's normalized units: mean squared error). The paper's third
// stage fine-tunes all but the expression network; trained that way (`train_encoder` false) the driving path cannot
// learn what its frozen expression latent does not hold, and on the simulated performance it did not generalize to
// frames it never saw (docs/asset.md). With the encoder trained too, the geometry decides what the encoder keeps of an
// image: the expression, not the head's pose or the camera's view. Created from the two finished nets (their weights
// copied); the expression VAE's decoder and view latent play no part. Untrained, it is the mapping's own driving path
// (encoder, then mapping), which is how the driven evaluation and inference apply a mapping that was not fine-tuned.
struct DrivingNetOptions {
  // Train the expression encoder with the mapping (false: only the mapping, the paper's choice).
  bool train_encoder = true;
  int threads = 0;
  absl::Status Validate() const;
};

class DrivingNet {
 public:
  // Errors: options out of range.
  static absl::StatusOr<std::unique_ptr<DrivingNet>> Create(const ExpressionVae& expression,
                                                            const LatentMapping& mapping,
                                                            const DrivingNetOptions& options);
  ~DrivingNet();
  DrivingNet(const DrivingNet&) = delete;
  DrivingNet& operator=(const DrivingNet&) = delete;

  // One Adam step on `batch` crops (B x 1 x I x I, 0..1, the caller's augmentation applied) and their frames'
  // geometry latents (B x geometry latent): the mean squared error in the mapping's normalized units, each dimension
  // weighed by its variance over the mean variance (the latent's own units, so a dimension the geometry VAE barely
  // uses counts for little).
  absl::StatusOr<double> TrainStep(const std::vector<float>& images, const std::vector<float>& targets, int batch,
                                   double learning_rate);
  // From now on TrainStep's loss is taken on the maps instead: the driven and the target latents decoded by a copy of
  // `geometry`'s decoder (frozen, not saved with this net), the squared difference in the geometry VAE's normalized
  // units weighed per texel by `weights` (S x S at its input size: 0 outside the face, more about the eyes and the
  // mouth). A latent error counts as much as it moves the face where the evaluation looks. Errors: a geometry VAE
  // whose latent is not the mapping's output, weights of another size.
  absl::Status UseMapLoss(const GeometryVae& geometry, const std::vector<float>& weights);
  // The geometry latents (B x geometry latent) of `batch` crops (B x 1 x I x I).
  absl::StatusOr<std::vector<float>> Drive(const std::vector<float>& images, int batch) const;
  absl::Status Save(const std::string& path) const;
  absl::Status Load(const std::string& path);
  const DrivingNetOptions& options() const;
  int input_size() const;  // the crops' pixels across
  int output() const;      // the geometry latent's size
  int64_t trained_parameters() const;

 private:
  using Impl = internal::DrivingNetNet;
  explicit DrivingNet(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// Multiply-adds of one forward pass of the geometry VAE on one map (its convolutions and linear layers), for
// benchmarks; a training step costs about three times that per map.
double GeometryVaeForwardMacs(const GeometryVaeOptions& o);

// The floor a net's training step is measured against (bench/asset_bench): one 3 x 3 convolution of `channels` to
// `channels` at size x size on a batch, forward and backward, timed over `steps` after a warm-up: multiply-adds a
// second (the backward counted as twice the forward).
absl::StatusOr<double> ConvFloorMacsPerSecond(int size, int channels, int batch, int steps, int threads);

}  // namespace stage::processing
