// `stage-process asset ...`: see asset_commands.h.
#include "asset_commands.h"

#include <iostream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/cli.h"

namespace stage::process {
namespace {

constexpr const char* kProgram = "stage-process";

}  // namespace

void AssetCommands::Add(CLI::App& parent) {
  app_ = parent.add_subcommand(
      "asset",
      "The neural facial asset (docs/asset.md): its dataset from a take and the training of its "
      "geometry VAE, and its evaluation (the expression and texture networks and inference are to come)");
  app_->require_subcommand(1);
  build_dataset_ = app_->add_subcommand(
      "build-dataset",
      "A take's frames as training samples: per frame the UV geometry map in the face template's layout (head "
      "frame, mm) and the head's pose, split into training frames, held-out contiguous blocks and one held-out "
      "expression sequence; one HDF5 file (default TAKE/derived/asset/dataset.h5)");
  build_dataset_->add_option("--take", dataset_.take_dir, "The take directory (takes/<take-id>)")->required();
  build_dataset_
      ->add_option("--source", source_,
                   "Where the geometry comes from: truth (the simulator's ground truth: a simulated take, or "
                   "stage-sim-render --ground-truth TAKE/ground_truth) or reconstruction (the template fit: run "
                   "stage-process fit first)")
      ->capture_default_str();
  build_dataset_->add_option("--frames", frames_, "Frames A:B (B excluded), A: to the end, or A")
      ->capture_default_str();
  build_dataset_->add_option("--output", dataset_.output, "The dataset file (default TAKE/derived/asset/dataset.h5)");
  build_dataset_->add_option("--geometry-size", dataset_.geometry_size, "Texels across the geometry map")
      ->capture_default_str()
      ->check(CLI::Range(16, 1024));
  build_dataset_
      ->add_option("--held-out-fraction", dataset_.held_out_fraction,
                   "Share of the frames (without the held-out sequence) held out as contiguous blocks")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 0.5));
  build_dataset_->add_option("--held-out-blocks", dataset_.held_out_blocks, "How many blocks they make")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  build_dataset_->add_option("--held-out-sequence", dataset_.held_out_sequence,
                             "The expression sequence held out whole (e.g. smile-3; default: the last the take holds "
                             "whole; none: no sequence)");
  build_dataset_
      ->add_option("--cameras", dataset_.cameras,
                   "Machine-vision cameras whose full-lit frames are cropped about the face, comma-separated "
                   "(default: every one the take recorded)")
      ->delimiter(',');
  build_dataset_->add_option("--calibration", dataset_.calibration,
                             "Where the cameras are (a calibration file or a directory with cameras.json, relative to "
                             "the take or absolute; default: the rig's nominal models)");
  build_dataset_->add_option("--image-size", dataset_.image_size, "Pixels across a crop")
      ->capture_default_str()
      ->check(CLI::Range(16, 512));
  build_dataset_->add_option("--crop-mm", dataset_.crop_mm, "The crop's side at the face, mm")
      ->capture_default_str()
      ->check(CLI::Range(50.0, 1000.0));
  build_dataset_->add_flag("--json", json_, "Print the summary as JSON on stdout");
  AddTrain();
}

void AssetCommands::AddTrain() {
  processing::AssetTrainJob& job = train_job_;
  processing::GeometryVaeOptions& g = job.geometry;
  train_ = app_->add_subcommand(
      "train",
      "Trains a network of the asset on a dataset (build-dataset's), resumably: checkpoints, loss.csv and loss.png, "
      "and at the end the net and its error on the held-out frames beside PCA's and the neutral frame's "
      "(docs/asset.md#training)");
  train_->add_option("--dataset", job.dataset, "The dataset file (build-dataset's)")->required();
  train_->add_option("--network", network_, "The network: geometry (the geometry VAE; the others are to come)")
      ->capture_default_str()
      ->check(CLI::IsMember({"geometry"}));
  train_->add_option("--output", job.output_dir, "The run's directory (default: the dataset's directory/geometry)");
  train_->add_option("--iterations", job.iterations, "Adam steps")
      ->capture_default_str()
      ->check(CLI::Range(1, 10000000));
  train_->add_option("--batch", job.batch, "Maps a step")->capture_default_str()->check(CLI::Range(1, 1024));
  train_->add_option("--learning-rate", job.learning_rate, "Adam's rate (the last 30 % of the steps at a fifth)")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  train_->add_option("--checkpoint-every", job.checkpoint_every, "Steps between checkpoints")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  train_->add_flag("--resume", job.resume, "Continue from the run directory's checkpoint (same options)");
  train_->add_option("--input-size", g.input_size, "Texels across the maps the net sees (the dataset's must divide)")
      ->capture_default_str();
  train_->add_option("--levels", g.levels, "Stride-2 levels of the encoder and decoder")->capture_default_str();
  train_->add_option("--base-channels", g.base_channels, "Channels at full resolution")->capture_default_str();
  train_->add_option("--max-channels", g.max_channels, "Channels at most")->capture_default_str();
  train_->add_option("--geometry-latent", g.geometry_latent, "Size of the geometry latent")->capture_default_str();
  train_->add_option("--pose-latent", g.pose_latent, "Size of the pose latent")->capture_default_str();
  train_->add_option("--kl-weight", g.kl_weight, "Weight of the KL terms")->capture_default_str();
  train_->add_option("--augment-rotation", job.augment_rotation_deg, "Random turns of the training maps, degrees")
      ->capture_default_str();
  train_->add_option("--augment-translation", job.augment_translation_mm, "Random shifts of the training maps, mm")
      ->capture_default_str();
  train_->add_option("--threads", g.threads, "Torch's threads (0: the cores this process may use)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  train_->add_option("--seed", g.seed, "The weights' initialization and the batches' draws")->capture_default_str();
  train_->add_flag("--json", json_, "Print the result as JSON on stdout");

  evaluate_ = app_->add_subcommand(
      "evaluate",
      "A trained geometry VAE against a dataset's frames (each split; the whole face's texels, and the template's "
      "vertices by region: face, eyes, mouth) beside PCA with as many components and the neutral frame");
  evaluate_->add_option("--dataset", evaluate_dataset_, "The dataset file")->required();
  evaluate_->add_option("--run", evaluate_run_, "The training run's directory (asset train's --output)")->required();
  evaluate_->add_flag("--json", json_, "Print the evaluation as JSON on stdout");
}

bool AssetCommands::Parsed() const { return app_ != nullptr && app_->parsed(); }

int AssetCommands::Run() {
  if (build_dataset_->parsed()) return BuildDataset();
  if (train_->parsed()) return Train();
  if (evaluate_->parsed()) return Evaluate();
  return 0;
}

int AssetCommands::BuildDataset() {
  if (auto s = ParseFrameRange("--frames", frames_, &dataset_.first_frame, &dataset_.last_frame); !s.ok()) {
    return ReportFatal(kProgram, s);
  }
  auto source = processing::ParseAssetSource(source_);
  if (!source.ok()) return ReportFatal(kProgram, source.status());
  dataset_.source = *source;
  ProgressLine bar("frames");
  dataset_.progress = [&bar](int64_t done, int64_t total) { bar.Update(done, total); };
  auto summary = processing::BuildAssetDataset(dataset_);
  bar.Finish();
  if (!summary.ok()) return ReportFatal(kProgram, summary.status());
  if (json_) {
    std::cout << nlohmann::json{{"dataset", summary->path},
                                {"source", processing::AssetSourceName(summary->source)},
                                {"geometry_size", summary->geometry_size},
                                {"frames", summary->frames},
                                {"train", summary->train},
                                {"held_out_block", summary->held_out_block},
                                {"held_out_sequence", summary->held_out_sequence},
                                {"sequence", summary->sequence},
                                {"sequences", summary->sequences.size()},
                                {"cameras", summary->cameras},
                                {"image_size", summary->image_size},
                                {"valid_texels", summary->valid_texels},
                                {"rms_from_mean_mm", summary->rms_from_mean_mm}}
                     .dump()
              << "\n";
  } else {
    std::cout << summary->frames << " frame(s) from the " << processing::AssetSourceName(summary->source) << " into "
              << summary->path << ": " << summary->train << " to train on, " << summary->held_out_block
              << " in held-out blocks, " << summary->held_out_sequence << " in the held-out sequence"
              << (summary->sequence.empty() ? " (none)" : " \"" + summary->sequence + "\"") << "; "
              << summary->cameras.size() << " camera(s) cropped"
              << "; " << static_cast<int64_t>(summary->valid_texels) << " texels a frame, " << summary->rms_from_mean_mm
              << " mm RMS about the mean\n";
  }
  return 0;
}

}  // namespace stage::process

namespace stage::process {

int AssetCommands::Train() {
  ProgressLine bar("steps");
  train_job_.progress = [&bar](int64_t step, int64_t total, const processing::GeometryLosses& l) {
    if (step % 10 == 0 || step == total) bar.Update(step, total, absl::StrFormat("loss %.4g", l.total));
    return true;
  };
  auto result = processing::TrainGeometryAsset(train_job_);
  bar.Finish();
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  if (json_) {
    nlohmann::json j = nlohmann::json::parse(processing::TrainedEvaluationJson(result->evaluation));
    std::cout << nlohmann::json{{"output_dir", result->output_dir},
                                {"steps", result->steps},
                                {"resumed_from", result->resumed_from},
                                {"parameters", result->parameters},
                                {"scale_mm", result->scale_mm},
                                {"final_loss", result->losses.empty() ? 0.0 : result->losses.back().total},
                                {"evaluation", j}}
                     .dump()
              << "\n";
  } else {
    std::cout << "geometry VAE (" << result->parameters << " weights) trained " << result->steps << " steps"
              << (result->resumed_from > 0 ? absl::StrCat(" (resumed at ", result->resumed_from, ")") : "") << " into "
              << result->output_dir << "\n"
              << "The maps encoded unmoved and decoded, against the truth (mm, at the net's resolution):\n"
              << processing::FormatTrainedEvaluation(result->evaluation);
  }
  return 0;
}

int AssetCommands::Evaluate() {
  auto result = processing::EvaluateGeometryAsset(evaluate_dataset_, evaluate_run_);
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  std::cout << (json_ ? processing::TrainedEvaluationJson(*result) + "\n"
                      : processing::FormatTrainedEvaluation(*result));
  return 0;
}

}  // namespace stage::process
