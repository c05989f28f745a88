// One network's resumable training in a run directory, whichever the network (asset_train.cc's geometry VAE,
// expression VAE and latent mapping): the steps, checkpoints at intervals and at the end, the losses as CSV and a
// plot, and a resume that ends bit for bit where an unbroken run ends. Torch-free: the net is reached through the
// loop's functions. The directory holds:
//   checkpoint-NNNNNN.pt  the net and its optimizer's state at the last checkpoint's step (TrainingLoop::save)
//   trainer.json          the step reached, its checkpoint's file, the generator's state and the options a resume
//                         must find the same; replaced atomically after the checkpoint is written, and the previous
//                         checkpoint removed after it, so a kill at any point leaves it naming a whole checkpoint
//   loss.csv, loss.png    every step's losses, and their curves (log scale)
#pragma once

#include <cstdint>
#include <functional>
#include <nlohmann/json.hpp>
#include <random>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/asset_train.h"

namespace stage::processing::internal {

struct TrainingLoop {
  std::string dir;   // the run's directory (made if missing)
  std::string what;  // the net, for messages ("expression VAE")
  // Every option a resume must find the same (the net's, the schedule's, the dataset's identity, the threads).
  nlohmann::json options;
  // The losses' names in the order `step` returns them, the total first; the plot draws the first three.
  std::vector<std::string> loss_names;
  // Its steps, rate (the last 30 % of the steps at a fifth of it), checkpoints and resume (the batch is `step`'s).
  TrainingSchedule schedule;
  uint64_t seed = 1;  // the generator's, for a fresh start
  std::function<absl::Status(const std::string&path)> save, load;
  // One step: a batch drawn from `rng`, trained at `learning_rate`; the losses in loss_names' order.
  std::function<absl::StatusOr<std::vector<double>>(std::mt19937_64& rng, double learning_rate)> step;
  // After every step: false stops the run (Cancelled) with its last checkpoint kept.
  std::function<bool(int64_t step, int64_t total, const std::vector<double>& losses)> progress;
};

struct TrainingOutcome {
  int64_t resumed_from = 0;                 // the checkpoint's step (0: a fresh start)
  std::vector<std::vector<double>> losses;  // every step's, from the first
};

// Runs the loop to its last step. A resume of other options is FailedPrecondition naming the option (or, with
// restart_if_different, a fresh start); a stopped run is Cancelled naming its checkpoint.
absl::StatusOr<TrainingOutcome> RunTraining(const TrainingLoop& loop);

// N(0, 1) from the engine alone (Box-Muller; no distribution object whose cached draw a checkpoint would miss), and
// uniform in [-half_range, half_range].
float Normal(std::mt19937_64& rng);
double Uniform(std::mt19937_64& rng, double half_range);

}  // namespace stage::processing::internal
