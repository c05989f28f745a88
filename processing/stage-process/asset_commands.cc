// `stage-process asset ...`: see asset_commands.h.
#include "asset_commands.h"

#include <iostream>
#include <nlohmann/json.hpp>

#include "stage/common/cli.h"

namespace stage::process {
namespace {

constexpr const char* kProgram = "stage-process";

}  // namespace

void AssetCommands::Add(CLI::App& parent) {
  app_ = parent.add_subcommand("asset",
                               "The neural facial asset (docs/asset.md): its dataset from a take, and (to come) its "
                               "training, inference and evaluation");
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
  build_dataset_->add_flag("--json", json_, "Print the summary as JSON on stdout");
}

bool AssetCommands::Parsed() const { return app_ != nullptr && app_->parsed(); }

int AssetCommands::Run() {
  if (build_dataset_->parsed()) return BuildDataset();
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
                                {"valid_texels", summary->valid_texels},
                                {"rms_from_mean_mm", summary->rms_from_mean_mm}}
                     .dump()
              << "\n";
  } else {
    std::cout << summary->frames << " frame(s) from the " << processing::AssetSourceName(summary->source) << " into "
              << summary->path << ": " << summary->train << " to train on, " << summary->held_out_block
              << " in held-out blocks, " << summary->held_out_sequence << " in the held-out sequence"
              << (summary->sequence.empty() ? " (none)" : " \"" + summary->sequence + "\"") << "; "
              << static_cast<int64_t>(summary->valid_texels) << " texels a frame, " << summary->rms_from_mean_mm
              << " mm RMS about the mean\n";
  }
  return 0;
}

}  // namespace stage::process
