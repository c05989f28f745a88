// Training the neural asset's networks on a dataset (docs/asset.md#training), each resumably in a run directory of its
// own (processing/src/training_run.h): the geometry VAE (DATASET's directory/geometry), the expression VAE
// (.../expression), the mapping from its latent to the geometry latent with both frozen (.../mapping) and the driving
// path fine-tuned (.../finetune), the stages of the paper's section 4.5; the texture VAE and its mapping
// (TrainTextureAsset, TrainTextureMapping below: .../texture, .../texture_mapping) run the same loop. Each run's
// directory holds:
//   checkpoint-NNNNNN.pt  the net and Adam's state at the last checkpoint's step
//   trainer.json       the step reached, its checkpoint's file, the generator's state, the options, the dataset's
//                      identity and the thread count (a resume must match them); replaced atomically after the
//                      checkpoint is written, and the previous checkpoint removed after it
//   loss.csv, loss.png every step's losses, and their curves (log scale)
//   evaluation.json    the held-out frames' error beside the baselines
// and its net at the end: geometry_vae.pt (and geometry_vae.torchscript.pt, the same as TorchScript, which Python's
// torch.jit.load runs: encode, decode), expression_vae.pt, mapping.pt, driving_net.pt. A run killed at any point
// resumes from its last checkpoint (`resume`) and ends bit for bit where an unbroken run of the same options and thread
// count ends.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/processing/asset_net.h"

namespace stage::processing {

// What every network's training shares.
struct TrainingSchedule {
  int iterations = 4000;        // Adam steps (1..10^7)
  int batch = 16;               // samples a step (1..1024)
  double learning_rate = 1e-3;  // > 0; the last 30 % of the steps at a fifth of it
  int checkpoint_every = 250;   // steps between checkpoints (1 and up)
  // Continue from the run directory's checkpoint (its options must be these); false: start anew (a checkpoint there
  // is replaced).
  bool resume = false;
  // With resume: a run of other options (or another dataset, or thread count) there is started anew instead of
  // refused (the worker's jobs: a job of changed options retrains).
  bool restart_if_different = false;
  absl::Status Validate() const;
};

struct AssetTrainJob {
  std::string dataset;     // stage-process asset build-dataset's file
  std::string output_dir;  // default: DATASET's directory/geometry
  GeometryVaeOptions geometry;
  // 6000 steps: at 64 x 64 on the 600-s simulated performance the ceiling driving can reach on the held-out blocks
  // fell from 0.27 / 0.41 / 0.88 mm (face / eyes / mouth) at 1500 steps to 0.13 / 0.11 / 0.32
  // (docs/asset.md#the-rate-and-the-length-of-the-training).
  TrainingSchedule schedule{.iterations = 6000};
  // The random rigid motion each training map is shown under (uniform in each axis): turns about the head's origin
  // up to this many degrees about x, y and z, and shifts up to this many mm along each.
  double augment_rotation_deg = 15;
  double augment_translation_mm = 10;
  // How many times a texel about the eyes' and the mouth's openings (the template's kEye and kMouth vertices' texels
  // and a ring about them) counts in the maps' losses against one elsewhere: the lids and the lips' inner edges move
  // most within a few texels, which a plain mean over the face smooths away (docs/asset.md#the-geometry-vae: at 10 the
  // held-out eyes come back at 0.30 mm against 1.26 mm unweighted). 1: every texel alike. 1..1000.
  double region_weight = 10;
  // Called after every step: (step, iterations, losses); false stops the run (Cancelled) after writing its
  // checkpoint's state as it last stood.
  std::function<bool(int64_t, int64_t, const GeometryLosses&)> progress;
  absl::Status Validate() const;
};

// Error of maps recovered by a model against the truth, mm, at the net's resolution: over every valid texel, and at
// the face template's vertices (the maps sampled there) by region, as the paper reports it: the face (the skin), the
// eyes (the lids about them) and the mouth (the lips' inner edges).
struct SplitError {
  int64_t frames = 0;
  double rmse_mm = 0, p99_mm = 0;
  double face_mm = 0, eyes_mm = 0, mouth_mm = 0;  // RMSE
};
inline constexpr double kMovedRotationDeg = 5, kMovedTranslationMm = 5;
struct TrainedEvaluation {
  // Each split of the dataset (train, held-out blocks, held-out sequence): the VAE's maps (encoded unmoved, the
  // geometry latent's mean decoded), PCA's with as many components as the geometry latent (fitted on the training
  // frames, the map projected), and the neutral frame's (the dataset's first frame, for every frame). vae_moved: the
  // VAE's maps of the input first moved rigidly (each frame by its own motion, seeded by its index, up to
  // kMovedRotationDeg about each axis and kMovedTranslationMm along it: a head pose a fit leaves off), against the
  // unmoved truth: what the pose augmentation buys (a geometry that does not shake as the pose estimate does).
  SplitError vae[3], vae_moved[3], pca[3], neutral[3];
};

struct AssetTrainResult {
  std::string output_dir;
  int64_t steps = 0;         // reached
  int64_t resumed_from = 0;  // the checkpoint's step (0: a fresh start)
  int64_t parameters = 0;
  float scale_mm = 0;                  // the training maps' spread about their mean
  std::vector<GeometryLosses> losses;  // every step's, from the first
  TrainedEvaluation evaluation;
};

absl::StatusOr<AssetTrainResult> TrainGeometryAsset(const AssetTrainJob& job);

// The evaluation of a finished run (its directory's trainer.json and geometry_vae.pt) on `dataset` (the one it trained
// on, or another of the same layout). Errors name the file.
absl::StatusOr<TrainedEvaluation> EvaluateGeometryAsset(const std::string& dataset, const std::string& run_dir);

// The expression VAE's training on the dataset's crops: triplets (frame a by camera i, frame a by camera j, frame b by
// camera i) of the training frames and the cameras not held out.
struct ExpressionTrainJob {
  std::string dataset;
  std::string output_dir;           // default: DATASET's directory/expression
  ExpressionVaeOptions expression;  // input_size: the dataset's crops' size must be a multiple of it
  // Cameras of the dataset whose crops the net never sees: the paper's held-out view, which the asset is then driven
  // from (at least two cameras must remain).
  std::vector<std::string> held_out_cameras;
  // 1500 steps of 8 triplets: the driving path's fine-tuning trains its encoder on from here, and the measured
  // chain started from this (docs/asset.md#the-default-training).
  TrainingSchedule schedule{.iterations = 1500, .batch = 8};
  std::function<bool(int64_t, int64_t, const ExpressionLosses&)> progress;
  absl::Status Validate() const;
};

// How the trained expression VAE does on each split (train, held-out blocks, held-out sequence): its crops' mean
// squared reconstruction (0..1 units) on the cameras it trained on and on those held out, and how much of its
// expression latent's spread over a split's crops lies between the cameras of one frame (0: the same latent from
// every view, as the swaps ask; 1: nothing shared).
struct ExpressionEvaluation {
  double reconstruction_trained[3] = {0, 0, 0}, reconstruction_held_out[3] = {0, 0, 0};
  double view_share[3] = {0, 0, 0};
};

struct ExpressionTrainResult {
  std::string output_dir;
  int64_t steps = 0, resumed_from = 0, parameters = 0;
  std::vector<ExpressionLosses> losses;
  std::vector<std::string> trained_cameras;
  ExpressionEvaluation evaluation;
};
absl::StatusOr<ExpressionTrainResult> TrainExpressionAsset(const ExpressionTrainJob& job);

// The mapping from the expression latent to the geometry latent, both VAEs frozen (their runs finished): pairs of a
// training frame's crop by a trained camera (its expression latent's mean) and the frame's map (its geometry
// latent's mean). At the end, the asset driven from every camera is evaluated (DrivenEvaluation, evaluation.json) and
// one frame drawn (driven.png: see EvaluateDrivenAsset).
struct MappingTrainJob {
  std::string dataset;
  std::string output_dir;      // default: DATASET's directory/mapping
  std::string geometry_run;    // default: DATASET's directory/geometry
  std::string expression_run;  // default: DATASET's directory/expression
  // The net (its input and output sizes are the VAEs' latents': left 0 here, they are set from the runs).
  LatentMappingOptions mapping{.input = 0, .output = 0};
  // The noise added to every training input, in units of the inputs' spread per dimension (0..2).
  double input_noise = 0.1;
  TrainingSchedule schedule{.iterations = 3000, .batch = 64};
  std::function<bool(int64_t, int64_t, double)> progress;
  absl::Status Validate() const;
};

// The asset driven from one camera's crops, as the paper's protocol: crop -> expression latent -> mapping -> geometry
// latent -> decoded map, against the frame's map, for each split (SplitError: texels, and vertices by region), per
// camera (those the expression VAE trained on, and the held-out ones the protocol is about); beside the geometry VAE
// encoding the frame's own map (the ceiling driving can reach) and the neutral frame.
struct DrivenEvaluation {
  struct Camera {
    std::string id;
    bool trained = false;
    SplitError error[3];
  };
  std::vector<Camera> cameras;
  SplitError autoencoded[3], neutral[3];
};

struct MappingTrainResult {
  std::string output_dir;
  int64_t steps = 0, resumed_from = 0, parameters = 0, pairs = 0;
  std::vector<double> losses;
  DrivenEvaluation evaluation;
};
absl::StatusOr<MappingTrainResult> TrainLatentMapping(const MappingTrainJob& job);

// The third stage (docs/asset.md#fine-tuning-the-driving-path): the driving path (DrivingNet: the expression VAE's
// encoder and the mapping) trained together on the training frames' geometry latents, from the finished runs of the
// stages before, on the mapping's pairs (a training frame's crop by a trained camera). Each crop is shown under a
// random jitter of its box (scale, turn, shift) and its exposure (gain, noise): a camera's crop box is fixed while the
// head moves in it, and the jitter stands in for the views and poses the frames do not hold. The run's directory
// (default DATASET's directory/finetune) holds the loop's files (training_run.h), driving_net.pt, evaluation.json (the
// paper's protocol, DrivenEvaluation) and driven.png, as the mapping's.
struct FineTuneJob {
  std::string dataset;
  std::string output_dir;  // default: DATASET's directory/finetune
  // Default: the mapping's run DATASET's directory/mapping; the geometry and expression runs the mapping's run was
  // trained from (its trainer.json) where they are still there, else DATASET's directory/geometry, /expression.
  std::string geometry_run, expression_run, mapping_run;
  DrivingNetOptions driving;
  // The jitter, uniform within each bound: scale by 1 +- jitter_scale, turn by +- jitter_rotation_deg about the
  // crop's centre, shift by +- jitter_shift of the crop's side along each axis, gain 1 +- jitter_gain, and normal
  // noise of jitter_noise (0..1 units) on every pixel. All 0: the crops as they are. The box's jitter twice that of
  // earlier defaults (0.05, 3 degrees, 0.05): on the 600-s simulated performance the held-out camera's eyes came to
  // 0.47 mm against 0.59 (docs/asset.md#the-rate-and-the-length-of-the-training).
  double jitter_scale = 0.1;       // 0..0.5
  double jitter_rotation_deg = 6;  // 0..45
  double jitter_shift = 0.1;       // 0..0.5
  double jitter_gain = 0.1;        // 0..0.9
  double jitter_noise = 0.01;      // 0..0.5
  // 48000 steps at 1e-3 over the expression VAE's default 16 channels: on the 600-s simulated performance at 64
  // pixels the held-out camera drove the held-out blocks to 0.34 / 0.39 / 1.02 mm (face / eyes / mouth); 72000 steps
  // gave 0.33 / 0.36 / 1.02, and at 8 channels 96000 steps 0.39 / 0.41 / 1.10; 3e-4 or 3e-3 did worse than 1e-3
  // (docs/asset.md#the-rate-and-the-length-of-the-training). About an hour on one core at 64 pixels.
  TrainingSchedule schedule{.iterations = 48000, .batch = 32, .learning_rate = 1e-3};
  // The loss: 0, on the geometry latents (DrivingNet::TrainStep); >= 1 (up to 1000), on the maps they decode to
  // (DrivingNet::UseMapLoss), over the texels the training frames hold, those about the eyes and the mouth weighing
  // this many times (as AssetTrainJob::region_weight).
  double map_loss_region_weight = 0;
  uint64_t seed = 1;  // the run's generator's (the batches, the jitter)
  std::function<bool(int64_t, int64_t, double)> progress;
  absl::Status Validate() const;
};
// The result: as the mapping's (its pairs, losses and the driven evaluation), of the fine-tuned path.
absl::StatusOr<MappingTrainResult> FineTuneDrivingAsset(const FineTuneJob& job);

// The driven evaluation of finished runs on `dataset` (an empty name: the run the fine-tuning's run, else the
// mapping's, was trained from where it is still there, else DATASET's directory/geometry, .../expression,
// .../mapping), and where `picture` names a PNG file, one frame drawn there as the mapping's training draws it into its
// run (driven.png: the middle frame of the held-out blocks, driven from the first held-out camera; its crop, the
// truth, the driven mesh and its error). `finetune_run`: the driving path fine-tuned (FineTuneDrivingAsset's run; ""
// names DATASET's directory/finetune), or "none": the mapping's path. Errors name the file.
absl::StatusOr<DrivenEvaluation> EvaluateDrivenAsset(const std::string& dataset, const std::string& geometry_run = "",
                                                     const std::string& expression_run = "",
                                                     const std::string& mapping_run = "",
                                                     const std::string& picture = "",
                                                     const std::string& finetune_run = "none");
std::string DrivenEvaluationJson(const DrivenEvaluation& e);
std::string FormatDrivenEvaluation(const DrivenEvaluation& e);
std::string ExpressionEvaluationJson(const ExpressionEvaluation& e);

// The texture VAE's training on the dataset's textures (its run: DATASET's directory/texture, texture_vae.pt): the
// training frames' textures at the net's size (the dataset's averaged down), the net's neutral textures their mean
// and its spread each channel's RMS about it.
struct TextureTrainJob {
  std::string dataset;
  std::string output_dir;     // default: DATASET's directory/texture
  TextureVaeOptions texture;  // channels: the dataset's (left as they are, checked)
  // The ablation without wrinkle maps (the paper's 6.3): the net decodes the textures themselves, its neutral
  // textures zero and its spread each channel's RMS about zero, instead of wrinkle maps over the training mean.
  bool direct = false;
  TrainingSchedule schedule;
  std::function<bool(int64_t, int64_t, const TextureLosses&)> progress;
  absl::Status Validate() const;
};

// Textures recovered against the dataset's, on the skin (texels of the face template's skin triangles, not the eyes'
// or the mouth's): the albedo's RMSE in 0..255 levels of its sRGB encoding (the paper's measure), the tangent-space
// normals' mean angle, and the specular intensity's mean relative error.
struct TextureSplitError {
  int64_t frames = 0;
  double albedo_levels = 0, normal_deg = 0, specular_relative = 0;
};
// Each split (train, held-out blocks, held-out sequence): the VAE's textures (encoded, the latent's mean decoded),
// PCA's with as many components as the latent (fitted on the training frames), and the neutral frame's (the dataset's
// first frame's, for every frame).
struct TextureEvaluation {
  TextureSplitError vae[3], pca[3], neutral[3];
};

struct TextureTrainResult {
  std::string output_dir;
  int64_t steps = 0, resumed_from = 0, parameters = 0;
  std::vector<TextureLosses> losses;
  TextureEvaluation evaluation;
};
// Errors: a dataset without textures (naming it and how to get them), sizes that do not divide.
absl::StatusOr<TextureTrainResult> TrainTextureAsset(const TextureTrainJob& job);
// The evaluation of a finished texture run on `dataset`.
absl::StatusOr<TextureEvaluation> EvaluateTextureAsset(const std::string& dataset, const std::string& run_dir);
std::string TextureEvaluationJson(const TextureEvaluation& e);
std::string FormatTextureEvaluation(const TextureEvaluation& e);

// The textures driven (docs/asset.md#driving-the-textures): an MLP from the geometry latent to the texture latent,
// both VAEs frozen, trained on the training frames (each frame's map's geometry latent mean -> its textures' texture
// latent mean; inputs noised as the mapping's). Our own design, where the paper maps the expression latent to both:
// whatever drives the geometry (the mapping, or the fine-tuned path, whose encoder no longer gives the expression
// VAE's latent) then drives the textures through it, one driving path. Its run: DATASET's directory/texture_mapping,
// texture_mapping.pt; its options hold the two VAE runs' identities.
struct TextureMappingJob {
  std::string dataset;
  std::string output_dir;                                 // default: DATASET's directory/texture_mapping
  std::string geometry_run;                               // default: DATASET's directory/geometry
  std::string texture_run;                                // default: DATASET's directory/texture
  LatentMappingOptions mapping{.input = 0, .output = 0};  // sizes set from the runs
  double input_noise = 0.1;                               // in units of the inputs' spread per dimension (0..2)
  TrainingSchedule schedule{.iterations = 3000, .batch = 64};
  std::function<bool(int64_t, int64_t, double)> progress;
  absl::Status Validate() const;
};

// Textures through the texture mapping, on the skin (TextureSplitError), per split: from each frame's own geometry
// latent (what the texture mapping can reach), and driven from each camera's crops where the asset has a driving
// path (its mapping run; through its fine-tuned path where one is trained); beside the texture VAE encoding the
// frame's own textures and the neutral frame.
struct TextureDrivenEvaluation {
  struct Camera {
    std::string id;
    bool trained = false;
    TextureSplitError error[3];
  };
  TextureSplitError from_geometry[3], autoencoded[3], neutral[3];
  std::vector<Camera> cameras;
  std::string driven_through;  // "finetune", "mapping", or empty where the asset has no driving path
};

struct TextureMappingResult {
  std::string output_dir;
  int64_t steps = 0, resumed_from = 0, parameters = 0;
  std::vector<double> losses;
  TextureDrivenEvaluation evaluation;
};
absl::StatusOr<TextureMappingResult> TrainTextureMapping(const TextureMappingJob& job);
// Finished runs evaluated on `dataset` (an empty name: the texture mapping's run beside the dataset; the geometry and
// texture runs it was trained from where they are still there, else beside the dataset).
absl::StatusOr<TextureDrivenEvaluation> EvaluateDrivenTextures(const std::string& dataset,
                                                               const std::string& geometry_run = "",
                                                               const std::string& texture_run = "",
                                                               const std::string& texture_mapping_run = "");
std::string TextureDrivenEvaluationJson(const TextureDrivenEvaluation& e);
std::string FormatTextureDrivenEvaluation(const TextureDrivenEvaluation& e);

// The evaluation as JSON, and as a table in words (the baselines beside the VAE).
std::string TrainedEvaluationJson(const TrainedEvaluation& e);
std::string FormatTrainedEvaluation(const TrainedEvaluation& e);

}  // namespace stage::processing
