// `stage-process asset ...`: see asset_commands.h.
#include "asset_commands.h"

#include <algorithm>
#include <filesystem>
#include <iostream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "stage/common/cli.h"

namespace stage::process {
namespace {

constexpr const char* kProgram = "stage-process";

}  // namespace

void AssetCommands::Add(CLI::App& parent) {
  app_ = parent.add_subcommand(
      "asset",
      "The neural facial asset (docs/asset.md): its dataset from a take and the training of its "
      "geometry VAE, expression VAE and the mapping between their latents, the fine-tuned driving path, the texture "
      "VAE and its mapping, their evaluation, and the asset driven from a camera's images");
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
  build_dataset_->add_option("--frame-step", dataset_.frame_step, "Every Nth of the frames the source holds")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000));
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
  build_dataset_
      ->add_option("--texture-size", dataset_.texture_size,
                   "Texels across the textures (albedo, specular, tangent-space normals), taken where the source has "
                   "them; 0: none")
      ->capture_default_str()
      ->check(CLI::IsMember({0}) | CLI::Range(16, 1024));
  build_dataset_
      ->add_option("--neutral-texture-size", dataset_.neutral_texture_size,
                   "Texels across the neutral (first) frame's textures kept at full resolution beside the dataset "
                   "(DATASET-neutral/), which inference adds the driven wrinkle maps to; 0: the source's own size; "
                   "-1: none")
      ->capture_default_str()
      ->check(CLI::IsMember({-1, 0}) | CLI::Range(16, 8192));
  build_dataset_->add_option("--image-size", dataset_.image_size, "Pixels across a crop")
      ->capture_default_str()
      ->check(CLI::Range(16, 512));
  build_dataset_->add_option("--crop-mm", dataset_.crop_mm, "The crop's side at the face, mm")
      ->capture_default_str()
      ->check(CLI::Range(50.0, 1000.0));
  build_dataset_->add_flag("--json", json_, "Print the summary as JSON on stdout");
  AddTrain();
  AddEvaluate();
  AddInfer();
}

void AssetCommands::AddTrain() {
  processing::AssetTrainJob& job = train_job_;
  processing::GeometryVaeOptions& g = job.geometry;
  processing::TrainingSchedule& schedule = job.schedule;
  train_ = app_->add_subcommand(
      "train",
      "Trains a network of the asset on a dataset (build-dataset's), resumably, each into a run directory of its "
      "own beside the dataset: checkpoints, loss.csv and loss.png, and at the end the net and its evaluation. The "
      "stages in order (docs/asset.md#training): geometry (the geometry VAE, on the maps), expression (the "
      "expression VAE, on the crops; --held-out-cameras keeps views out of it), mapping (expression latent to "
      "geometry latent, both VAEs frozen: the asset driven from every camera is evaluated at the end) and finetune "
      "(the expression encoder and the mapping trained together on the geometry latents, the crops jittered: the "
      "driving path inference uses; evaluated as the mapping); texture (the texture VAE, on the dataset's textures: "
      "wrinkle maps over their mean) and texture-mapping (geometry latent to texture latent, both VAEs frozen: "
      "whatever drives the geometry then drives the textures)");
  train_->add_option("--dataset", job.dataset, "The dataset file (build-dataset's)")->required();
  train_
      ->add_option("--network", network_,
                   "The network: geometry, expression, mapping, finetune, texture or texture-mapping")
      ->capture_default_str()
      ->check(CLI::IsMember({"geometry", "expression", "mapping", "finetune", "texture", "texture-mapping"}));
  train_->add_option(
      "--output", job.output_dir,
      "The run's directory (default: the dataset's directory/geometry, /expression, /mapping, /finetune, "
      "/texture or /texture_mapping)");
  train_
      ->add_option("--iterations", schedule.iterations,
                   "Adam steps (default: geometry 6000, expression 1500, mapping 3000, finetune 48000, texture "
                   "4000, texture-mapping 3000)")
      ->check(CLI::Range(1, 10000000));
  train_
      ->add_option("--batch", schedule.batch,
                   "Samples a step (default 16; the expression's 8, the mappings' 64, finetune's 32)")
      ->check(CLI::Range(1, 1024));
  train_
      ->add_option("--learning-rate", schedule.learning_rate,
                   "Adam's rate (the last 30 % of the steps at a fifth; default 1e-3)")
      ->check(CLI::PositiveNumber);
  train_->add_option("--checkpoint-every", schedule.checkpoint_every, "Steps between checkpoints")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  train_->add_flag("--resume", schedule.resume, "Continue from the run directory's checkpoint (same options)");
  // The VAEs' trunks (geometry, expression and texture; each network keeps its own default where none is given).
  train_->add_option("--input-size", g.input_size,
                     "Texels (pixels) across the maps (crops) the net sees, the dataset's a multiple of it (default: "
                     "geometry and expression 64, texture 128)");
  train_->add_option("--levels", g.levels,
                     "Stride-2 levels of the encoder and decoder (default: geometry and expression 4, texture 5)");
  train_->add_option("--base-channels", g.base_channels,
                     "Channels at full resolution (default: geometry and texture 8, expression 16)");
  train_->add_option("--max-channels", g.max_channels, "Channels at most")->capture_default_str();
  train_->add_option("--kl-weight", g.kl_weight, "Weight of the KL terms")->capture_default_str();
  // The geometry VAE's.
  train_->add_option("--geometry-latent", g.geometry_latent, "geometry: size of the geometry latent")
      ->capture_default_str();
  train_->add_option("--pose-latent", g.pose_latent, "geometry: size of the pose latent")->capture_default_str();
  train_
      ->add_option("--augment-rotation", job.augment_rotation_deg,
                   "geometry: random turns of the training maps, degrees")
      ->capture_default_str();
  train_
      ->add_option("--augment-translation", job.augment_translation_mm,
                   "geometry: random shifts of the training maps, mm")
      ->capture_default_str();
  train_
      ->add_option("--region-weight", job.region_weight,
                   "geometry: how many times a texel about the eyes' and the mouth's openings counts in the maps' "
                   "losses (1: as any other)")
      ->capture_default_str();
  AddTrainNetworkOptions();
  train_->add_option("--threads", g.threads, "Torch's threads (0: the cores this process may use)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  train_->add_option("--seed", g.seed, "The weights' initialization and the batches' draws")->capture_default_str();
  train_->add_flag("--json", json_, "Print the result as JSON on stdout");
}

// The options of the expression VAE and the mapping (the geometry VAE's are its job's, bound above).
void AssetCommands::AddTrainNetworkOptions() {
  // The expression VAE's.
  processing::ExpressionVaeOptions& e = expression_job_.expression;
  train_->add_option("--expression-latent", e.expression_latent, "expression: size of the expression latent")
      ->capture_default_str();
  train_->add_option("--view-latent", e.view_latent, "expression: size of the view latent")->capture_default_str();
  train_->add_option("--swap-weight", e.swap_weight, "expression: weight of the latent swaps")->capture_default_str();
  train_->add_option("--cycle-weight", e.cycle_weight, "expression: weight of the cycle term")->capture_default_str();
  train_
      ->add_option("--held-out-cameras", expression_job_.held_out_cameras,
                   "expression: cameras whose crops it never sees (the view the asset is driven from), "
                   "comma-separated")
      ->delimiter(',');
  train_->add_option("--texture-latent", texture_job_.texture.texture_latent, "texture: size of the texture latent")
      ->capture_default_str();
  train_->add_flag("--direct-textures", texture_job_.direct,
                   "texture: decode the textures themselves, not wrinkle maps over the training mean (the paper's "
                   "ablation)");
  // The mapping's.
  processing::LatentMappingOptions& m = mapping_job_.mapping;
  train_->add_option("--hidden", m.hidden, "mapping: hidden units")->capture_default_str();
  train_->add_option("--layers", m.layers, "mapping: linear layers")->capture_default_str();
  train_
      ->add_option("--input-noise", mapping_job_.input_noise,
                   "mapping: noise added to its inputs, in units of their spread")
      ->capture_default_str();
  train_->add_option("--texture-run", texture_mapping_job_.texture_run,
                     "texture-mapping: the texture VAE's run (default: the dataset's directory/texture)");
  train_->add_option(
      "--geometry-run", mapping_job_.geometry_run,
      "mapping, finetune, texture-mapping: the geometry VAE's run (default: finetune: the one the mapping's run was "
      "trained from; else the dataset's directory/geometry)");
  train_->add_option("--expression-run", mapping_job_.expression_run,
                     "mapping, finetune: the expression VAE's run (default: finetune: the one the mapping's run was "
                     "trained from; else the dataset's directory/expression)");
  // The fine-tuning's.
  processing::FineTuneJob& f = finetune_job_;
  train_->add_option("--mapping-run", f.mapping_run,
                     "finetune: the mapping's run (default: the dataset's directory/mapping)");
  train_->add_flag("--freeze-encoder", freeze_encoder_,
                   "finetune: train only the mapping, the expression encoder frozen (the paper's choice)");
  train_->add_option("--jitter-scale", f.jitter_scale, "finetune: the crops' random scale, +- this fraction")
      ->capture_default_str();
  train_->add_option("--jitter-rotation", f.jitter_rotation_deg, "finetune: the crops' random turn, +- degrees")
      ->capture_default_str();
  train_->add_option("--jitter-shift", f.jitter_shift, "finetune: the crops' random shift, +- this fraction of a side")
      ->capture_default_str();
  train_->add_option("--jitter-gain", f.jitter_gain, "finetune: the crops' random gain, 1 +- this")
      ->capture_default_str();
  train_->add_option("--jitter-noise", f.jitter_noise, "finetune: noise on the crops' pixels (0..1 units)")
      ->capture_default_str();
  train_
      ->add_option("--map-loss", f.map_loss_region_weight,
                   "finetune: 0 (the loss on the geometry latents), or the loss on the maps they decode to with the "
                   "eyes' and the mouth's texels weighing this many times (1..1000)")
      ->capture_default_str();
}

void AssetCommands::AddEvaluate() {
  evaluate_ = app_->add_subcommand(
      "evaluate",
      "A trained asset against a dataset's frames (each split; the whole face's texels, and the template's "
      "vertices by region: face, eyes, mouth): the geometry VAE's run beside PCA and the neutral frame, or the "
      "asset driven from each camera's crops (--network mapping, or finetune for the fine-tuned driving path: the "
      "paper's protocol), or the texture VAE's run (--network texture: albedo levels, normal degrees, specular error "
      "on the skin, beside PCA and the neutral frame), or the texture mapping's run (--network texture-mapping: the "
      "textures driven from each camera)");
  evaluate_->add_option("--dataset", evaluate_dataset_, "The dataset file")->required();
  evaluate_
      ->add_option("--network", evaluate_network_,
                   "What to evaluate: geometry, mapping (the asset driven through the mapping), finetune (driven "
                   "through the fine-tuned path), texture or texture-mapping")
      ->capture_default_str()
      ->check(CLI::IsMember({"geometry", "mapping", "finetune", "texture", "texture-mapping"}));
  evaluate_->add_option("--run", evaluate_run_,
                        "The run's directory (default: the dataset's directory/geometry, /mapping, /finetune, "
                        "/texture or /texture_mapping)");
  evaluate_->add_option("--texture-run", evaluate_texture_run_,
                        "texture-mapping: the texture VAE's run (default: the one the run was trained from, else the "
                        "dataset's directory/texture)");
  evaluate_->add_option("--mapping-run", evaluate_mapping_run_,
                        "finetune: the mapping's run (default: the one the run was trained from, else the dataset's "
                        "directory/mapping)");
  evaluate_->add_option("--geometry-run", evaluate_geometry_run_,
                        "mapping, finetune, texture-mapping: the geometry VAE's run (default: the one the run was "
                        "trained from, else the dataset's directory/geometry)");
  evaluate_->add_option("--expression-run", evaluate_expression_run_,
                        "mapping, finetune: the expression VAE's run (default: the one the run was trained from, else "
                        "the dataset's directory/expression)");
  evaluate_->add_option("--picture", evaluate_picture_,
                        "--network mapping: draw one frame into this PNG (the middle held-out block frame driven from "
                        "the held-out camera: its crop, the truth, the driven mesh, the error)");
  evaluate_->add_flag("--json", json_, "Print the evaluation as JSON on stdout");
}

void AssetCommands::AddInfer() {
  processing::AssetInferOptions& o = infer_;
  infer_app_ = app_->add_subcommand(
      "infer",
      "Drives the trained asset from one camera's images (docs/asset.md#inference): each cropped as the dataset "
      "crops that camera, encoded, mapped and decoded to the frame's UV geometry map and the face template's mesh "
      "(OUTPUT/frame-NNNNNN/crop.png, geometry_map.exr, mesh.obj; the meshes as glTF animations, "
      "OUTPUT/animation-NNNNNN.glb; frames.json)");
  infer_app_->add_option("--dataset", o.dataset, "The asset's dataset (the trained runs beside it)")->required();
  infer_app_->add_option("--camera", o.camera, "The camera the images are of (one the dataset cropped)")->required();
  auto* take = infer_app_->add_option("--take", o.take_dir, "A take whose full-lit frames of the camera drive it");
  auto* video = infer_app_->add_option(
      "--video", o.video,
      "Or a video file (or an image sequence, dir/frame-%04d.png) of the camera's view, display-referred 8-bit");
  take->excludes(video);
  infer_app_->add_option("--frames", infer_frames_, "The take's frames A:B (B excluded), A: to the end, or A")
      ->capture_default_str();
  infer_app_->add_option("--output", o.output_dir,
                         "The output directory (default TAKE/derived/asset/infer/CAMERA, or VIDEO-asset beside it)");
  infer_app_->add_option("--geometry-run", o.geometry_run,
                         "The geometry VAE's run (default: the one the fine-tuning's run, else the mapping's, was "
                         "trained from; else beside the dataset)");
  infer_app_->add_option("--expression-run", o.expression_run,
                         "The expression VAE's run (default: as the geometry VAE's)");
  infer_app_->add_option("--mapping-run", o.mapping_run,
                         "The mapping's run (default: the one the fine-tuning's run was trained from, else beside "
                         "the dataset)");
  infer_app_->add_option("--texture-mapping-run", o.texture_mapping_run,
                         "The texture mapping the textures are driven through (default: the dataset's "
                         "directory/texture_mapping where it holds a finished run, else no textures; none: none)");
  infer_app_->add_option("--texture-run", o.texture_run,
                         "The texture VAE's run (default: the one the texture mapping was trained from, else beside "
                         "the dataset)");
  infer_app_->add_option("--finetune-run", o.finetune_run,
                         "The fine-tuned driving path's run (default: beside the dataset where there is one, else "
                         "the mapping alone; none: the mapping alone)");
  infer_app_->add_flag("--no-meshes", no_meshes_, "Write no mesh.obj");
  infer_app_
      ->add_option("--gltf-segment-frames", o.gltf_segment_frames,
                   "Frames per glTF file (a morph target and shape key per frame; 0: no glTF)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  infer_app_->add_option("--fps", o.gltf_frames_per_second, "The glTF animation's frames per second")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  infer_app_->add_option("--threads", o.threads, "Torch's threads (0: the cores this process may use)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  infer_app_->add_flag("--json", json_, "Print the result as JSON on stdout");
}

int AssetCommands::Infer() {
  processing::AssetInferOptions& o = infer_;
  if (!o.take_dir.empty()) {
    if (auto s = ParseFrameRange("--frames", infer_frames_, &o.first_frame, &o.last_frame); !s.ok()) {
      return ReportFatal(kProgram, s);
    }
  } else if (infer_app_->count("--frames") > 0) {
    return ReportFatal(kProgram, absl::InvalidArgumentError("--frames are a take's: a --video is read whole"));
  }
  o.meshes = !no_meshes_;
  ProgressLine bar("frames");
  o.progress = [&bar](int64_t done) {  // the count is not known ahead (a video's, a take's lost frames)
    if (done % 10 == 0) bar.Message(absl::StrCat(done, " frame(s) driven"));
  };
  auto result = processing::InferAsset(o);
  bar.Finish();
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  if (json_) {
    std::cout << nlohmann::json{{"output_dir", result->output_dir},
                                {"frames", result->frames},
                                {"gltf", result->gltf_files},
                                {"textures", result->textures},
                                {"texture_size", result->texture_size}}
                     .dump()
              << "\n";
  } else {
    std::cout << result->frames.size() << " frame(s) of " << o.camera << " drove the asset into " << result->output_dir
              << " (" << result->gltf_files.size() << " glTF animation(s)"
              << (result->textures ? absl::StrCat("; textures ", result->texture_size, " texels across")
                                   : "; no textures: no texture mapping trained")
              << ")\n";
  }
  return 0;
}

bool AssetCommands::Parsed() const { return app_ != nullptr && app_->parsed(); }

int AssetCommands::Run() {
  if (build_dataset_->parsed()) return BuildDataset();
  if (train_->parsed()) return Train();
  if (evaluate_->parsed()) return Evaluate();
  if (infer_app_->parsed()) return Infer();
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
                                {"texture_size", summary->texture_size},
                                {"textures_note", summary->textures_note},
                                {"neutral_texture_size", summary->neutral_texture_size},
                                {"neutral_textures_dir", summary->neutral_textures_dir},
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
              << "; textures "
              << (summary->texture_size > 0 ? absl::StrCat(summary->texture_size, " texels across")
                                            : summary->textures_note)
              << (summary->neutral_texture_size > 0
                      ? absl::StrCat(" (the neutral frame's at ", summary->neutral_texture_size, " in ",
                                     summary->neutral_textures_dir, ")")
                      : "")
              << "; " << static_cast<int64_t>(summary->valid_texels) << " texels a frame, " << summary->rms_from_mean_mm
              << " mm RMS about the mean\n";
  }
  return 0;
}

}  // namespace stage::process

namespace stage::process {

namespace {

// The options given that `network` does not take (each names its network in its help: "geometry: ...").
absl::Status CheckOptionsFor(const CLI::App& app, const std::string& network) {
  const std::vector<std::pair<std::string, std::vector<std::string>>> only = {
      {"--input-size", {"geometry", "expression", "texture"}},
      {"--levels", {"geometry", "expression", "texture"}},
      {"--base-channels", {"geometry", "expression", "texture"}},
      {"--max-channels", {"geometry", "expression", "texture"}},
      {"--kl-weight", {"geometry", "expression", "texture"}},
      {"--texture-latent", {"texture"}},
      {"--direct-textures", {"texture"}},
      {"--geometry-latent", {"geometry"}},
      {"--pose-latent", {"geometry"}},
      {"--augment-rotation", {"geometry"}},
      {"--augment-translation", {"geometry"}},
      {"--region-weight", {"geometry"}},
      {"--expression-latent", {"expression"}},
      {"--view-latent", {"expression"}},
      {"--swap-weight", {"expression"}},
      {"--cycle-weight", {"expression"}},
      {"--held-out-cameras", {"expression"}},
      {"--hidden", {"mapping", "texture-mapping"}},
      {"--layers", {"mapping", "texture-mapping"}},
      {"--input-noise", {"mapping", "texture-mapping"}},
      {"--geometry-run", {"mapping", "finetune", "texture-mapping"}},
      {"--texture-run", {"texture-mapping"}},
      {"--expression-run", {"mapping", "finetune"}},
      {"--mapping-run", {"finetune"}},
      {"--freeze-encoder", {"finetune"}},
      {"--jitter-scale", {"finetune"}},
      {"--jitter-rotation", {"finetune"}},
      {"--jitter-shift", {"finetune"}},
      {"--jitter-gain", {"finetune"}},
      {"--jitter-noise", {"finetune"}},
      {"--map-loss", {"finetune"}}};
  for (const auto& [option, networks] : only) {
    if (app.count(option) > 0 && std::find(networks.begin(), networks.end(), network) == networks.end()) {
      return absl::InvalidArgumentError(absl::StrCat(option, " is not an option of the ", network, " network"));
    }
  }
  return absl::OkStatus();
}

// `job`'s schedule: its own defaults (each network's), with what the command line gave of the shared options.
void TakeGivenSchedule(const CLI::App& train, const processing::TrainingSchedule& given,
                       processing::TrainingSchedule* job) {
  if (train.count("--iterations") > 0) job->iterations = given.iterations;
  if (train.count("--batch") > 0) job->batch = given.batch;
  if (train.count("--learning-rate") > 0) job->learning_rate = given.learning_rate;
  job->checkpoint_every = given.checkpoint_every;
  job->resume = given.resume;
}

// The expression's or the texture VAE's trunk: its own defaults, with what the command line gave of the options bound
// to the geometry VAE's (`given`); threads and seed as given or their shared defaults.
template <typename Trunk>
void TakeGivenTrunk(const CLI::App& train, const processing::GeometryVaeOptions& given, Trunk* o) {
  if (train.count("--input-size") > 0) o->input_size = given.input_size;
  if (train.count("--levels") > 0) o->levels = given.levels;
  if (train.count("--base-channels") > 0) o->base_channels = given.base_channels;
  if (train.count("--max-channels") > 0) o->max_channels = given.max_channels;
  if (train.count("--kl-weight") > 0) o->kl_weight = given.kl_weight;
  o->threads = given.threads;
  o->seed = given.seed;
}

}  // namespace

int AssetCommands::Train() {
  if (auto s = CheckOptionsFor(*train_, network_); !s.ok()) return ReportFatal(kProgram, s);
  if (network_ == "expression") return TrainExpression();
  if (network_ == "mapping") return TrainMapping();
  if (network_ == "finetune") return FineTune();
  if (network_ == "texture") return TrainTexture();
  if (network_ == "texture-mapping") return TrainTextureMapping();
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

int AssetCommands::TrainExpression() {
  processing::ExpressionTrainJob& job = expression_job_;
  const processing::GeometryVaeOptions& g = train_job_.geometry;
  job.dataset = train_job_.dataset;
  job.output_dir = train_job_.output_dir;
  TakeGivenSchedule(*train_, train_job_.schedule, &job.schedule);
  TakeGivenTrunk(*train_, g, &job.expression);
  ProgressLine bar("steps");
  job.progress = [&bar](int64_t step, int64_t total, const processing::ExpressionLosses& l) {
    if (step % 10 == 0 || step == total) bar.Update(step, total, absl::StrFormat("loss %.4g", l.total));
    return true;
  };
  auto result = processing::TrainExpressionAsset(job);
  bar.Finish();
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  const processing::ExpressionEvaluation& e = result->evaluation;
  if (json_) {
    std::cout << nlohmann::json{{"output_dir", result->output_dir},
                                {"steps", result->steps},
                                {"resumed_from", result->resumed_from},
                                {"parameters", result->parameters},
                                {"trained_cameras", result->trained_cameras},
                                {"final_loss", result->losses.empty() ? 0.0 : result->losses.back().total},
                                {"evaluation", nlohmann::json::parse(processing::ExpressionEvaluationJson(e))}}
                     .dump()
              << "\n";
    return 0;
  }
  std::cout << "expression VAE (" << result->parameters << " weights) trained " << result->steps << " steps"
            << (result->resumed_from > 0 ? absl::StrCat(" (resumed at ", result->resumed_from, ")") : "")
            << " on the crops of " << absl::StrJoin(result->trained_cameras, ", ") << " into " << result->output_dir
            << "\n";
  const char* names[3] = {"train", "held-out blocks", "held-out sequence"};
  std::cout << absl::StrFormat("%-18s %-28s %-28s %s\n", "split", "reconstruction (trained cams)",
                               "reconstruction (held out)", "expression latent's share between views");
  for (int s = 0; s < 3; ++s) {
    std::cout << absl::StrFormat("%-18s %-28.5f %-28.5f %.3f\n", names[s], e.reconstruction_trained[s],
                                 e.reconstruction_held_out[s], e.view_share[s]);
  }
  return 0;
}

int AssetCommands::TrainTexture() {
  processing::TextureTrainJob& job = texture_job_;
  const processing::GeometryVaeOptions& g = train_job_.geometry;
  job.dataset = train_job_.dataset;
  job.output_dir = train_job_.output_dir;
  TakeGivenSchedule(*train_, train_job_.schedule, &job.schedule);
  TakeGivenTrunk(*train_, g, &job.texture);
  ProgressLine bar("steps");
  job.progress = [&bar](int64_t step, int64_t total, const processing::TextureLosses& l) {
    if (step % 10 == 0 || step == total) bar.Update(step, total, absl::StrFormat("loss %.4g", l.total));
    return true;
  };
  auto result = processing::TrainTextureAsset(job);
  bar.Finish();
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  if (json_) {
    std::cout << nlohmann::json{{"output_dir", result->output_dir},
                                {"steps", result->steps},
                                {"resumed_from", result->resumed_from},
                                {"parameters", result->parameters},
                                {"final_loss", result->losses.empty() ? 0.0 : result->losses.back().total},
                                {"evaluation",
                                 nlohmann::json::parse(processing::TextureEvaluationJson(result->evaluation))}}
                     .dump()
              << "\n";
    return 0;
  }
  std::cout << "texture VAE (" << result->parameters << " weights) trained " << result->steps << " steps"
            << (result->resumed_from > 0 ? absl::StrCat(" (resumed at ", result->resumed_from, ")") : "") << " into "
            << result->output_dir << "\n"
            << "The textures encoded and decoded, against the dataset's (at the net's resolution):\n"
            << processing::FormatTextureEvaluation(result->evaluation);
  return 0;
}

int AssetCommands::TrainTextureMapping() {
  processing::TextureMappingJob& job = texture_mapping_job_;
  job.dataset = train_job_.dataset;
  job.output_dir = train_job_.output_dir;
  job.geometry_run = mapping_job_.geometry_run;
  TakeGivenSchedule(*train_, train_job_.schedule, &job.schedule);
  job.mapping.hidden = mapping_job_.mapping.hidden;
  job.mapping.layers = mapping_job_.mapping.layers;
  job.input_noise = mapping_job_.input_noise;
  job.mapping.threads = train_job_.geometry.threads;
  job.mapping.seed = train_job_.geometry.seed;
  ProgressLine bar("steps");
  job.progress = [&bar](int64_t step, int64_t total, double loss) {
    if (step % 50 == 0 || step == total) bar.Update(step, total, absl::StrFormat("loss %.4g", loss));
    return true;
  };
  auto result = processing::TrainTextureMapping(job);
  bar.Finish();
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  if (json_) {
    std::cout << nlohmann::json{{"output_dir", result->output_dir},
                                {"steps", result->steps},
                                {"resumed_from", result->resumed_from},
                                {"parameters", result->parameters},
                                {"final_loss", result->losses.empty() ? 0.0 : result->losses.back()},
                                {"evaluation",
                                 nlohmann::json::parse(processing::TextureDrivenEvaluationJson(result->evaluation))}}
                     .dump()
              << "\n";
    return 0;
  }
  std::cout << "texture mapping (" << result->parameters << " weights) trained " << result->steps << " steps"
            << (result->resumed_from > 0 ? absl::StrCat(" (resumed at ", result->resumed_from, ")") : "") << " into "
            << result->output_dir << "\n"
            << "The textures through it, against the dataset's (at the texture net's resolution):\n"
            << processing::FormatTextureDrivenEvaluation(result->evaluation);
  return 0;
}

int AssetCommands::TrainMapping() {
  processing::MappingTrainJob& job = mapping_job_;
  job.dataset = train_job_.dataset;
  job.output_dir = train_job_.output_dir;
  TakeGivenSchedule(*train_, train_job_.schedule, &job.schedule);
  job.mapping.threads = train_job_.geometry.threads;
  job.mapping.seed = train_job_.geometry.seed;
  ProgressLine bar("steps");
  job.progress = [&bar](int64_t step, int64_t total, double loss) {
    if (step % 50 == 0 || step == total) bar.Update(step, total, absl::StrFormat("loss %.4g", loss));
    return true;
  };
  auto result = processing::TrainLatentMapping(job);
  bar.Finish();
  return PrintDriven("latent mapping", result);
}

int AssetCommands::FineTune() {
  processing::FineTuneJob& job = finetune_job_;
  job.dataset = train_job_.dataset;
  job.output_dir = train_job_.output_dir;
  job.geometry_run = mapping_job_.geometry_run;
  job.expression_run = mapping_job_.expression_run;
  TakeGivenSchedule(*train_, train_job_.schedule, &job.schedule);
  job.driving.train_encoder = !freeze_encoder_;
  job.seed = train_job_.geometry.seed;
  job.driving.threads = train_job_.geometry.threads;
  ProgressLine bar("steps");
  job.progress = [&bar](int64_t step, int64_t total, double loss) {
    if (step % 10 == 0 || step == total) bar.Update(step, total, absl::StrFormat("loss %.4g", loss));
    return true;
  };
  auto result = processing::FineTuneDrivingAsset(job);
  bar.Finish();
  return PrintDriven(freeze_encoder_ ? "driving path (the mapping; the encoder frozen)"
                                     : "driving path (the expression encoder and the mapping)",
                     result);
}

int AssetCommands::PrintDriven(const std::string& what, const absl::StatusOr<processing::MappingTrainResult>& result) {
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  if (json_) {
    std::cout << nlohmann::json{{"output_dir", result->output_dir},
                                {"steps", result->steps},
                                {"resumed_from", result->resumed_from},
                                {"parameters", result->parameters},
                                {"pairs", result->pairs},
                                {"final_loss", result->losses.empty() ? 0.0 : result->losses.back()},
                                {"evaluation",
                                 nlohmann::json::parse(processing::DrivenEvaluationJson(result->evaluation))}}
                     .dump()
              << "\n";
    return 0;
  }
  std::cout << what << " (" << result->parameters << " weights) trained " << result->steps << " steps on "
            << result->pairs << " crops into " << result->output_dir << "\n"
            << "The asset driven from each camera's crops, against the truth (mm, at the geometry net's "
               "resolution):\n"
            << processing::FormatDrivenEvaluation(result->evaluation);
  return 0;
}

int AssetCommands::Evaluate() {
  if (evaluate_network_ != "finetune" && evaluate_->count("--mapping-run") > 0) {
    return ReportFatal(kProgram, absl::InvalidArgumentError("--mapping-run is an option of --network finetune"));
  }
  if (evaluate_network_ == "mapping" || evaluate_network_ == "finetune") {
    const bool finetune = evaluate_network_ == "finetune";
    auto result = processing::EvaluateDrivenAsset(evaluate_dataset_, evaluate_geometry_run_, evaluate_expression_run_,
                                                  finetune ? evaluate_mapping_run_ : evaluate_run_, evaluate_picture_,
                                                  finetune ? evaluate_run_ : "none");
    if (!result.ok()) return ReportFatal(kProgram, result.status());
    std::cout << (json_ ? processing::DrivenEvaluationJson(*result) + "\n"
                        : processing::FormatDrivenEvaluation(*result));
    return 0;
  }
  if (evaluate_network_ != "texture-mapping" && evaluate_->count("--texture-run") > 0) {
    return ReportFatal(kProgram, absl::InvalidArgumentError("--texture-run is an option of --network texture-mapping"));
  }
  if (evaluate_network_ == "texture-mapping") {
    if (evaluate_->count("--expression-run") > 0 || evaluate_->count("--picture") > 0) {
      return ReportFatal(kProgram, absl::InvalidArgumentError(
                                       "--expression-run and --picture are options of --network mapping and finetune"));
    }
    auto result = processing::EvaluateDrivenTextures(evaluate_dataset_, evaluate_geometry_run_, evaluate_texture_run_,
                                                     evaluate_run_);
    if (!result.ok()) return ReportFatal(kProgram, result.status());
    std::cout << (json_ ? processing::TextureDrivenEvaluationJson(*result) + "\n"
                        : processing::FormatTextureDrivenEvaluation(*result));
    return 0;
  }
  if (evaluate_->count("--geometry-run") > 0 || evaluate_->count("--expression-run") > 0 ||
      evaluate_->count("--picture") > 0) {
    return ReportFatal(
        kProgram, absl::InvalidArgumentError(
                      "--geometry-run, --expression-run and --picture are options of --network mapping and finetune"));
  }
  const bool texture = evaluate_network_ == "texture";
  const std::string run =
      evaluate_run_.empty()
          ? (std::filesystem::path(evaluate_dataset_).parent_path() / (texture ? "texture" : "geometry")).string()
          : evaluate_run_;
  if (texture) {
    auto result = processing::EvaluateTextureAsset(evaluate_dataset_, run);
    if (!result.ok()) return ReportFatal(kProgram, result.status());
    std::cout << (json_ ? processing::TextureEvaluationJson(*result) + "\n"
                        : processing::FormatTextureEvaluation(*result));
    return 0;
  }
  auto result = processing::EvaluateGeometryAsset(evaluate_dataset_, run);
  if (!result.ok()) return ReportFatal(kProgram, result.status());
  std::cout << (json_ ? processing::TrainedEvaluationJson(*result) + "\n"
                      : processing::FormatTrainedEvaluation(*result));
  return 0;
}

}  // namespace stage::process
