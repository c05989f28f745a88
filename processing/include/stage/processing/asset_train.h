// Training the neural asset's networks on a dataset (docs/asset.md#training), resumably: the geometry VAE so far
// (asset_net.h). Writes to the run's directory:
//   checkpoint-NNNNNN.pt  the net and Adam's state at the last checkpoint's step
//   trainer.json       the step reached, its checkpoint's file, the generator's state, the options, the dataset's
//                      identity and the thread count (a resume must match them); replaced atomically after the
//                      checkpoint is written, and the previous checkpoint removed after it
//   loss.csv, loss.png every step's losses, and their curves (log scale)
//   geometry_vae.pt    the trained net (at the end), and geometry_vae.torchscript.pt, the same as TorchScript (Python's
//                      torch.jit.load runs it: encode, decode)
//   evaluation.json    the held-out frames' error beside the baselines (TrainedEvaluation)
// A run killed at any point resumes from its last checkpoint (`resume`) and ends bit for bit where an unbroken run
// of the same options and thread count ends.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/processing/asset_net.h"

namespace stage::processing {

struct AssetTrainJob {
  std::string dataset;     // stage-process asset build-dataset's file
  std::string output_dir;  // default: DATASET's directory/geometry
  GeometryVaeOptions geometry;
  int iterations = 4000;        // Adam steps (1..10^7)
  int batch = 16;               // maps a step (1..1024)
  double learning_rate = 1e-3;  // > 0; the last 30 % of the steps at a fifth of it
  int checkpoint_every = 250;   // steps between checkpoints (1 and up)
  // The random rigid motion each training map is shown under (uniform in each axis): turns about the head's origin
  // up to this many degrees about x, y and z, and shifts up to this many mm along each.
  double augment_rotation_deg = 15;
  double augment_translation_mm = 10;
  // Continue from the run directory's checkpoint (its options must be these); false: start anew (a checkpoint there
  // is replaced).
  bool resume = false;
  // With resume: a run of other options (or another dataset, or thread count) there is started anew instead of
  // refused (the worker's jobs: a job of changed options retrains).
  bool restart_if_different = false;
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
struct TrainedEvaluation {
  // Each split of the dataset (train, held-out blocks, held-out sequence): the VAE's maps (encoded unmoved, the
  // geometry latent's mean decoded), PCA's with as many components as the geometry latent (fitted on the training
  // frames, the map projected), and the neutral frame's (the dataset's first frame, for every frame).
  SplitError vae[3], pca[3], neutral[3];
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

// The evaluation as JSON, and as a table in words (the baselines beside the VAE).
std::string TrainedEvaluationJson(const TrainedEvaluation& e);
std::string FormatTrainedEvaluation(const TrainedEvaluation& e);

}  // namespace stage::processing
