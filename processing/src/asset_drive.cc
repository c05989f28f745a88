// The asset driven from images: the expression VAE's training on a dataset's crops, the mapping of its latent to the
// geometry latent, and the asset driven from one camera evaluated as the paper's protocol (see asset_train.h).
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "asset_train_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/processing/asset_train.h"
#include "stage/processing/warp_net.h"
#include "training_run.h"

namespace stage::processing {
namespace fs = std::filesystem;
using asset_internal::Crops;
using asset_internal::CropsAt;
using asset_internal::DrivenAsset;
using asset_internal::ImageValid;
using asset_internal::LoadDrivenAsset;
using asset_internal::MeanAndSpread;
using asset_internal::NetMaps;
using asset_internal::PreparedData;
using asset_internal::RunId;
using asset_internal::TrainedCameras;
using internal::Normal;

namespace asset_internal {

absl::StatusOr<Crops> CropsAt(const AssetDataset& d, int size) {
  if (d.cameras.empty() || d.images.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat(d.path,
                     ": the dataset holds no crops (build it from a take whose cameras recorded full-lit "
                     "frames: stage-sim-render --take, or a recorded take)"));
  }
  if (d.image_size % size != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(d.path, ": its crops (", d.image_size, " pixels across) do not divide into the net's ", size));
  }
  Crops c;
  c.size = size;
  c.cameras = static_cast<int>(d.cameras.size());
  const size_t count = static_cast<size_t>(d.frames()) * c.cameras;
  c.pixels.assign(count * c.Pixels(), 0.f);
  const size_t in = static_cast<size_t>(d.image_size) * d.image_size;
  for (size_t i = 0; i < count; ++i) {
    asset_internal::CropToNetInput(d.images.data() + i * in, d.image_size, size, c.pixels.data() + i * c.Pixels());
  }
  return c;
}

bool ImageValid(const AssetDataset& d, int64_t frame, int camera) {
  return d.image_valid[static_cast<size_t>(frame) * d.cameras.size() + camera] != 0;
}

absl::StatusOr<std::vector<int>> TrainedCameras(const AssetDataset& d, const std::vector<std::string>& held_out) {
  for (const std::string& id : held_out) {
    if (std::find(d.cameras.begin(), d.cameras.end(), id) == d.cameras.end()) {
      return absl::NotFoundError(
          absl::StrCat(d.path, ": camera \"", id, "\" is not among its crops' (", absl::StrJoin(d.cameras, ", "), ")"));
    }
  }
  std::vector<int> out;
  for (int c = 0; c < static_cast<int>(d.cameras.size()); ++c) {
    if (std::find(held_out.begin(), held_out.end(), d.cameras[c]) == held_out.end()) out.push_back(c);
  }
  if (out.size() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(d.path, ": ", out.size(), " camera(s) left to train on; the view swaps need two"));
  }
  return out;
}

}  // namespace asset_internal

namespace {

// Triplets: frame a by camera i, frame a by camera j != i, frame b != a by camera i, all of training frames and
// trained cameras that recorded them.
class TripletSampler {
 public:
  TripletSampler(const AssetDataset& d, const Crops& crops, const std::vector<int>& cameras)
      : d_(d), crops_(crops), cameras_(cameras) {
    for (int64_t f : asset_internal::FramesOf(d, SampleSplit::kTrain)) {
      int seen = 0;
      for (int c : cameras) seen += ImageValid(d, f, c) ? 1 : 0;
      if (seen >= 2) frames_.push_back(f);
    }
  }
  bool usable() const { return frames_.size() >= 2; }
  ExpressionBatch Draw(int batch, int latents, std::mt19937_64& rng) const {
    ExpressionBatch b;
    b.batch = batch;
    auto append = [&](std::vector<float>* to, int64_t f, int c) {
      to->insert(to->end(), crops_.At(f, c), crops_.At(f, c) + crops_.Pixels());
    };
    for (int n = 0; n < batch; ++n) {
      int64_t a = 0, other = 0;
      int i = 0, j = 0;
      do {
        a = frames_[rng() % frames_.size()];
        i = cameras_[rng() % cameras_.size()];
        j = cameras_[rng() % cameras_.size()];
      } while (i == j || !ImageValid(d_, a, i) || !ImageValid(d_, a, j));
      do {
        other = frames_[rng() % frames_.size()];
      } while (other == a || !ImageValid(d_, other, i));
      append(&b.anchor, a, i);
      append(&b.same_expression, a, j);
      append(&b.same_view, other, i);
    }
    for (int n = 0; n < 3 * batch * latents; ++n) b.noise.push_back(Normal(rng));
    return b;
  }

 private:
  const AssetDataset& d_;
  const Crops& crops_;
  const std::vector<int>& cameras_;
  std::vector<int64_t> frames_;
};

nlohmann::json ExpressionOptionsJson(const ExpressionTrainJob& job, const std::string& dataset_id) {
  const ExpressionVaeOptions& e = job.expression;
  nlohmann::json j = {{"network", "expression"},
                      {"input_size", e.input_size},
                      {"levels", e.levels},
                      {"base_channels", e.base_channels},
                      {"max_channels", e.max_channels},
                      {"expression_latent", e.expression_latent},
                      {"view_latent", e.view_latent},
                      {"kl_weight", e.kl_weight},
                      {"swap_weight", e.swap_weight},
                      {"cycle_weight", e.cycle_weight},
                      {"seed", e.seed},
                      {"held_out_cameras", job.held_out_cameras},
                      {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
                      {"dataset_id", dataset_id},
                      {"threads", TorchThreadCount(e.threads)}};
  asset_internal::AddScheduleJson(job.schedule, &j);
  return j;
}

// Every crop's latents' means (frames x cameras rows of expression + view latents), in batches.
absl::StatusOr<std::vector<float>> EncodeAll(const ExpressionVae& net, const Crops& crops) {
  const size_t count = crops.pixels.size() / crops.Pixels();
  const int64_t latents = net.options().expression_latent + net.options().view_latent;
  std::vector<float> out;
  out.reserve(count * static_cast<size_t>(latents));
  constexpr size_t kBatch = 32;
  for (size_t i = 0; i < count; i += kBatch) {
    const size_t n = std::min(kBatch, count - i);
    const std::vector<float> images(crops.pixels.begin() + static_cast<std::ptrdiff_t>(i * crops.Pixels()),
                                    crops.pixels.begin() + static_cast<std::ptrdiff_t>((i + n) * crops.Pixels()));
    STAGE_ASSIGN_OR_RETURN(const std::vector<float> z, net.Encode(images, static_cast<int>(n)));
    out.insert(out.end(), z.begin(), z.end());
  }
  return out;
}

absl::StatusOr<ExpressionEvaluation> EvaluateExpression(const ExpressionVae& net, const AssetDataset& d,
                                                        const Crops& crops, const std::vector<int>& trained) {
  STAGE_ASSIGN_OR_RETURN(const std::vector<float> z, EncodeAll(net, crops));
  const int latents = net.options().expression_latent + net.options().view_latent;
  const int e = net.options().expression_latent;
  ExpressionEvaluation out;
  for (int s = 0; s < 3; ++s) {
    double se[2] = {0, 0}, n[2] = {0, 0};
    std::vector<double> all_mean(e, 0);
    double within = 0, total = 0, count = 0;
    std::vector<std::vector<double>> frame_means;
    const std::vector<int64_t> frames = asset_internal::FramesOf(d, static_cast<SampleSplit>(s));
    for (int64_t f : frames) {
      std::vector<double> mean(e, 0);
      int seen = 0;
      for (int c = 0; c < crops.cameras; ++c) {
        if (!ImageValid(d, f, c)) continue;
        const size_t row = static_cast<size_t>(f) * crops.cameras + c;
        const std::vector<float> latent(z.begin() + static_cast<std::ptrdiff_t>(row * latents),
                                        z.begin() + static_cast<std::ptrdiff_t>((row + 1) * latents));
        STAGE_ASSIGN_OR_RETURN(const std::vector<float> image, net.Decode(latent, 1));
        const int held = std::find(trained.begin(), trained.end(), c) == trained.end() ? 1 : 0;
        for (size_t p = 0; p < crops.Pixels(); ++p) se[held] += std::pow(image[p] - crops.At(f, c)[p], 2);
        n[held] += static_cast<double>(crops.Pixels());
        if (held) continue;
        for (int k = 0; k < e; ++k) mean[k] += latent[k], all_mean[k] += latent[k];
        ++seen;
        ++count;
      }
      for (int k = 0; k < e; ++k) mean[k] /= std::max(1, seen);
      frame_means.push_back(std::move(mean));
    }
    for (int k = 0; k < e; ++k) all_mean[k] /= std::max(1.0, count);
    for (size_t i = 0; i < frames.size(); ++i) {
      for (int c : trained) {
        if (!ImageValid(d, frames[i], c)) continue;
        const size_t row = static_cast<size_t>(frames[i]) * crops.cameras + c;
        for (int k = 0; k < e; ++k) {
          const double v = z[row * latents + k];
          within += std::pow(v - frame_means[i][k], 2);
          total += std::pow(v - all_mean[k], 2);
        }
      }
    }
    out.reconstruction_trained[s] = n[0] > 0 ? se[0] / n[0] : 0;
    out.reconstruction_held_out[s] = n[1] > 0 ? se[1] / n[1] : 0;
    out.view_share[s] = total > 0 ? within / total : 0;
  }
  return out;
}

}  // namespace

namespace asset_internal {

absl::StatusOr<DrivenAsset> LoadDrivenAsset(const std::string& dataset, const std::string& geometry_run,
                                            const std::string& expression_run, int threads) {
  DrivenAsset a;
  STAGE_ASSIGN_OR_RETURN(a.geometry, asset_internal::LoadGeometryRun(geometry_run, dataset, &a.data, threads));
  STAGE_ASSIGN_OR_RETURN(a.expression, asset_internal::LoadExpressionNet(expression_run, threads, &a.held_out));
  STAGE_ASSIGN_OR_RETURN(a.trained, TrainedCameras(a.data.dataset, a.held_out));
  STAGE_ASSIGN_OR_RETURN(a.crops, CropsAt(a.data.dataset, a.expression->options().input_size));
  const NetMaps& m = a.data.maps;
  for (int64_t f = 0; f < a.data.dataset.frames(); ++f) {
    STAGE_ASSIGN_OR_RETURN(const std::vector<float> z, a.geometry->Encode(m.maps[f], m.valid[f], 1));
    a.geometry_latents.insert(a.geometry_latents.end(), z.begin(), z.begin() + a.GeometrySize());
  }
  return a;
}

absl::Status Drive(DrivenAsset* a) {
  const size_t count = a->crops.pixels.size() / a->crops.Pixels();
  a->driven.clear();
  a->driven.reserve(count * a->GeometrySize());
  // Without a fine-tuned path, the expression VAE's encoder and the mapping as they stand: the same function.
  std::unique_ptr<DrivingNet> mapped;
  const DrivingNet* driver = a->driver.get();
  if (driver == nullptr) {
    STAGE_ASSIGN_OR_RETURN(mapped,
                           DrivingNet::Create(*a->expression, *a->mapping,
                                              {.train_encoder = false, .threads = a->expression->options().threads}));
    driver = mapped.get();
  }
  constexpr size_t kBatch = 32;
  for (size_t i = 0; i < count; i += kBatch) {
    const size_t n = std::min(kBatch, count - i);
    const std::vector<float> images(a->crops.pixels.begin() + static_cast<std::ptrdiff_t>(i * a->crops.Pixels()),
                                    a->crops.pixels.begin() + static_cast<std::ptrdiff_t>((i + n) * a->crops.Pixels()));
    STAGE_ASSIGN_OR_RETURN(const std::vector<float> z, driver->Drive(images, static_cast<int>(n)));
    a->driven.insert(a->driven.end(), z.begin(), z.end());
  }
  return absl::OkStatus();
}

absl::Status RunDrivenTraining(internal::TrainingLoop loop,
                               const std::function<bool(int64_t, int64_t, double)>& progress,
                               const std::string& net_file, DrivenAsset* a, MappingTrainResult* result) {
  if (progress) {
    loop.progress = [&](int64_t step, int64_t total, const std::vector<double>& l) {
      return progress(step, total, l[0]);
    };
  }
  STAGE_ASSIGN_OR_RETURN(const internal::TrainingOutcome outcome, internal::RunTraining(loop));
  result->resumed_from = outcome.resumed_from;
  for (const auto& l : outcome.losses) result->losses.push_back(l[0]);
  result->steps = loop.schedule.iterations;
  STAGE_RETURN_IF_ERROR(loop.save(result->output_dir + "/" + net_file));
  STAGE_RETURN_IF_ERROR(Drive(a));
  STAGE_ASSIGN_OR_RETURN(result->evaluation, EvaluateDriven(*a));
  STAGE_RETURN_IF_ERROR(
      WriteFileAtomically(result->output_dir + "/evaluation.json", DrivenEvaluationJson(result->evaluation) + "\n"));
  return WritePicture(*a, result->output_dir + "/driven.png");
}

absl::StatusOr<DrivenEvaluation> EvaluateDriven(const DrivenAsset& a) {
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  const AssetDataset& d = a.data.dataset;
  const NetMaps& m = a.data.maps;
  absl::Status failed;
  auto decode = [&](const std::vector<float>& z) {
    absl::StatusOr<std::vector<float>> map = a.geometry->Decode(z, 1);
    if (!map.ok()) failed = map.status();
    return map.ok() ? *map : std::vector<float>(m.maps[0].size(), 0.f);
  };
  DrivenEvaluation e;
  for (int s = 0; s < 3; ++s) {
    const std::vector<int64_t> frames = asset_internal::FramesOf(d, static_cast<SampleSplit>(s));
    e.autoencoded[s] = asset_internal::Error(m, face, frames, [&](int64_t f) {
      const auto begin = a.geometry_latents.begin() + static_cast<std::ptrdiff_t>(f * a.GeometrySize());
      return decode(std::vector<float>(begin, begin + a.GeometrySize()));
    });
    e.neutral[s] = asset_internal::Error(m, face, frames, [&](int64_t) { return m.maps[0]; });
  }
  for (int c = 0; c < a.crops.cameras; ++c) {
    DrivenEvaluation::Camera camera;
    camera.id = d.cameras[c];
    camera.trained = std::find(a.trained.begin(), a.trained.end(), c) != a.trained.end();
    for (int s = 0; s < 3; ++s) {
      std::vector<int64_t> frames;
      for (int64_t f : asset_internal::FramesOf(d, static_cast<SampleSplit>(s))) {
        if (ImageValid(d, f, c)) frames.push_back(f);
      }
      camera.error[s] = asset_internal::Error(m, face, frames, [&](int64_t f) { return decode(a.DrivenOf(f, c)); });
    }
    e.cameras.push_back(camera);
  }
  if (!failed.ok()) return failed;
  return e;
}

absl::Status WritePicture(const DrivenAsset& a, const std::string& path) {
  const AssetDataset& d = a.data.dataset;
  std::vector<int64_t> frames = asset_internal::FramesOf(d, SampleSplit::kHeldOutBlock);
  const bool held_out_frame = !frames.empty();
  if (frames.empty()) frames = a.data.train;
  if (frames.empty()) return absl::FailedPreconditionError(absl::StrCat(d.path, ": no frame to draw"));
  const int64_t f = frames[frames.size() / 2];
  std::vector<int> order;
  for (const std::string& id : a.held_out) {
    order.push_back(static_cast<int>(std::find(d.cameras.begin(), d.cameras.end(), id) - d.cameras.begin()));
  }
  order.insert(order.end(), a.trained.begin(), a.trained.end());
  const auto camera = std::find_if(order.begin(), order.end(), [&](int c) { return ImageValid(d, f, c); });
  if (camera == order.end()) {
    return absl::FailedPreconditionError(absl::StrCat(d.path, ": no camera recorded frame ", d.frame[f]));
  }
  const bool held_out_camera = camera - order.begin() < static_cast<std::ptrdiff_t>(a.held_out.size());
  const std::vector<float> z = a.DrivenOf(f, *camera);
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  asset_internal::DrivenPicture p;
  p.title = absl::StrFormat("frame %d (%s), driven from camera %s (%s): the geometry map in the head's frame",
                            d.frame[f], held_out_frame ? "a held-out block" : "trained on", d.cameras[*camera],
                            held_out_camera ? "held out" : "trained on");
  p.camera_label = absl::StrCat(d.cameras[*camera], "'s crop");
  p.crop = d.images.data() + (static_cast<size_t>(f) * d.cameras.size() + *camera) * d.image_size * d.image_size;
  p.crop_size = d.image_size;
  p.truth = a.data.maps.maps[f];
  p.valid = a.data.maps.valid[f];
  STAGE_ASSIGN_OR_RETURN(p.driven, a.geometry->Decode(z, 1));
  p.size = a.data.maps.size;
  p.face = &face;
  return asset_internal::WriteDrivenPicture(path, p);
}

std::vector<std::pair<int64_t, int>> MappingPairs(const DrivenAsset& a) {
  std::vector<std::pair<int64_t, int>> out;
  for (int64_t f : a.data.train) {
    for (int c : a.trained) {
      if (ImageValid(a.data.dataset, f, c)) out.emplace_back(f, c);
    }
  }
  return out;
}

void MeanAndSpread(const std::vector<std::vector<float>>& rows, int width, std::vector<float>* mean,
                   std::vector<float>* spread) {
  mean->assign(width, 0.f);
  spread->assign(width, 0.f);
  std::vector<double> sum(width, 0), sum2(width, 0);
  for (const auto& r : rows) {
    for (int k = 0; k < width; ++k) sum[k] += r[k], sum2[k] += static_cast<double>(r[k]) * r[k];
  }
  const double n = std::max<size_t>(1, rows.size());
  for (int k = 0; k < width; ++k) {
    (*mean)[k] = static_cast<float>(sum[k] / n);
    (*spread)[k] = static_cast<float>(std::max(1e-6, std::sqrt(std::max(0.0, sum2[k] / n - std::pow(sum[k] / n, 2)))));
  }
}

absl::StatusOr<std::string> RunId(const std::string& run_dir) {
  STAGE_ASSIGN_OR_RETURN(const std::string trainer, ReadFileToString(run_dir + "/trainer.json", "training run"));
  return absl::StrFormat("%016x", Fnv1a64(trainer));
}

namespace {
// A run's directory as a run's options record it: absolute, normalized.
std::string RecordedRunDir(const std::string& dir) { return fs::absolute(dir).lexically_normal().string(); }
}  // namespace

absl::Status AddRunIdentities(std::initializer_list<std::pair<const char*, std::string>> runs, nlohmann::json* j) {
  for (const auto& [name, dir] : runs) {
    (*j)[absl::StrCat(name, "_run")] = RecordedRunDir(dir);
    STAGE_ASSIGN_OR_RETURN((*j)[absl::StrCat(name, "_run_id")], RunId(dir));
  }
  return absl::OkStatus();
}

absl::Status CheckTrainedFrom(const std::string& run_dir, const nlohmann::json& o, const char* trained,
                              std::initializer_list<std::pair<const char*, std::string>> runs) {
  for (const auto& [name, dir] : runs) {
    STAGE_ASSIGN_OR_RETURN(const std::string id, RunId(dir));
    if (o.value(absl::StrCat(name, "_run_id"), "") != id) {
      // A run of another directory than the one given: name it (the caller took the default); the same directory:
      // it was trained again since.
      const std::string refused = absl::StrCat(run_dir, ": ", trained, " from another ", name, " run than ", dir);
      const std::string from = o.value(absl::StrCat(name, "_run"), "");
      if (!from.empty() && from != RecordedRunDir(dir)) {
        return absl::FailedPreconditionError(
            absl::StrCat(refused, ": from ", from, " (name it: --", name, "-run ", from, ")"));
      }
      return absl::FailedPreconditionError(absl::StrCat(refused, " (trained again since?): train it again"));
    }
  }
  return absl::OkStatus();
}

}  // namespace asset_internal

namespace {

absl::StatusOr<nlohmann::json> MappingOptionsJson(const MappingTrainJob& job, const LatentMappingOptions& o,
                                                  const std::string& dataset_id, const std::string& geometry_run,
                                                  const std::string& expression_run) {
  nlohmann::json j = {{"network", "mapping"},
                      {"input", o.input},
                      {"output", o.output},
                      {"hidden", o.hidden},
                      {"layers", o.layers},
                      {"seed", o.seed},
                      {"input_noise", job.input_noise},
                      {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
                      {"dataset_id", dataset_id},
                      {"threads", TorchThreadCount(o.threads)}};
  STAGE_RETURN_IF_ERROR(
      asset_internal::AddRunIdentities({{"geometry", geometry_run}, {"expression", expression_run}}, &j));
  asset_internal::AddScheduleJson(job.schedule, &j);
  return j;
}

// The mapping's net for `a`, its targets normalized over the training pairs.
absl::StatusOr<std::unique_ptr<LatentMapping>> CreateMapping(const DrivenAsset& a, LatentMappingOptions o,
                                                             const std::vector<std::pair<int64_t, int>>& pairs) {
  o.input = a.ExpressionSize();
  o.output = a.GeometrySize();
  std::vector<std::vector<float>> targets;
  for (const auto& [f, c] : pairs) {
    const auto begin = a.geometry_latents.begin() + static_cast<std::ptrdiff_t>(f * o.output);
    targets.emplace_back(begin, begin + o.output);
  }
  std::vector<float> mean, spread;
  MeanAndSpread(targets, o.output, &mean, &spread);
  return LatentMapping::Create(o, mean, spread);
}

}  // namespace

namespace asset_internal {

absl::StatusOr<DrivenAsset> LoadDriven(const std::string& dataset, const std::string& geometry_run,
                                       const std::string& expression_run, const std::string& mapping_run,
                                       const std::string& finetune_run, int threads) {
  const DrivenRuns runs = ResolveDrivenRuns(dataset, geometry_run, expression_run, mapping_run, finetune_run);
  STAGE_ASSIGN_OR_RETURN(DrivenAsset a, LoadDrivenAsset(dataset, runs.geometry, runs.expression, threads));
  STAGE_ASSIGN_OR_RETURN(a.mapping, LoadMappingNet(runs.mapping, a.ExpressionSize(), a.GeometrySize(), threads));
  if (!finetune_run.empty()) {
    STAGE_ASSIGN_OR_RETURN(a.driver, LoadDrivingNet(finetune_run, runs.geometry, runs.expression, runs.mapping,
                                                    *a.expression, *a.mapping, threads));
  }
  STAGE_RETURN_IF_ERROR(Drive(&a));
  return a;
}

void CropToNetInput(const uint8_t* crop, int size, int input, float* out) {
  const int k = size / input;
  for (int y = 0; y < input; ++y) {
    for (int x = 0; x < input; ++x) {
      int sum = 0;
      for (int dy = 0; dy < k; ++dy) {
        for (int dx = 0; dx < k; ++dx) sum += crop[static_cast<size_t>(y * k + dy) * size + x * k + dx];
      }
      out[static_cast<size_t>(y) * input + x] = static_cast<float>(sum) / (255.f * k * k);
    }
  }
}

absl::StatusOr<std::unique_ptr<ExpressionVae>> LoadExpressionNet(const std::string& run_dir, int threads,
                                                                 std::vector<std::string>* held_out) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, RunOptions(run_dir, "expression"));
  ExpressionVaeOptions options;
  options.threads = threads;
  STAGE_RETURN_IF_ERROR(ReadIntOptions(run_dir, o,
                                       {{"input_size", &options.input_size},
                                        {"levels", &options.levels},
                                        {"base_channels", &options.base_channels},
                                        {"max_channels", &options.max_channels},
                                        {"expression_latent", &options.expression_latent},
                                        {"view_latent", &options.view_latent}}));
  if (!o.contains("held_out_cameras") || !o["held_out_cameras"].is_array()) {
    return absl::InvalidArgumentError(absl::StrCat(run_dir, "/trainer.json: option held_out_cameras is missing"));
  }
  *held_out = o["held_out_cameras"].get<std::vector<std::string>>();
  STAGE_ASSIGN_OR_RETURN(auto net, ExpressionVae::Create(options));
  STAGE_RETURN_IF_ERROR(net->Load(run_dir + "/expression_vae.pt"));
  return net;
}

absl::StatusOr<std::unique_ptr<LatentMapping>> LoadMappingNet(const std::string& run_dir, int input, int output,
                                                              int threads, const std::string& network) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, RunOptions(run_dir, network));
  LatentMappingOptions options;
  options.threads = threads;
  STAGE_RETURN_IF_ERROR(ReadIntOptions(run_dir, o,
                                       {{"input", &options.input},
                                        {"output", &options.output},
                                        {"hidden", &options.hidden},
                                        {"layers", &options.layers}}));
  if (options.input != input || options.output != output) {
    return absl::FailedPreconditionError(absl::StrCat(run_dir, ": maps ", options.input, " to ", options.output,
                                                      " latents, the VAEs have ", input, " and ", output));
  }
  // The normalization is the trained net's (buffers of its weights, loaded below).
  STAGE_ASSIGN_OR_RETURN(
      auto net, LatentMapping::Create(options, std::vector<float>(output, 0.f), std::vector<float>(output, 1.f)));
  STAGE_RETURN_IF_ERROR(net->Load(run_dir + "/" + network + ".pt"));
  return net;
}

}  // namespace asset_internal

absl::Status ExpressionTrainJob::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("expression training: no dataset");
  STAGE_RETURN_IF_ERROR(expression.Validate());
  return schedule.Validate();
}

absl::StatusOr<ExpressionTrainResult> TrainExpressionAsset(const ExpressionTrainJob& job) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  STAGE_ASSIGN_OR_RETURN(const AssetDataset d, ReadAssetDataset(job.dataset));
  STAGE_ASSIGN_OR_RETURN(const Crops crops, CropsAt(d, job.expression.input_size));
  STAGE_ASSIGN_OR_RETURN(const std::vector<int> trained, TrainedCameras(d, job.held_out_cameras));
  const TripletSampler sampler(d, crops, trained);
  if (!sampler.usable()) {
    return absl::FailedPreconditionError(
        absl::StrCat(job.dataset, ": fewer than two training frames seen by two of the cameras trained on"));
  }
  ExpressionTrainResult result;
  result.output_dir = asset_internal::RunDir(job.output_dir, job.dataset, "expression");
  for (int c : trained) result.trained_cameras.push_back(d.cameras[c]);
  STAGE_ASSIGN_OR_RETURN(auto net, ExpressionVae::Create(job.expression));
  result.parameters = net->parameter_count();
  const int latents = job.expression.expression_latent + job.expression.view_latent;
  internal::TrainingLoop loop;
  loop.dir = result.output_dir;
  loop.what = "expression VAE";
  loop.options = ExpressionOptionsJson(job, asset_internal::DatasetId(d));
  loop.loss_names = {"total", "reconstruction", "expression_swap", "view_swap", "cycle", "kl"};
  loop.schedule = job.schedule;
  loop.seed = job.expression.seed;
  loop.save = [&net](const std::string& path) { return net->Save(path); };
  loop.load = [&net](const std::string& path) { return net->Load(path); };
  loop.step = [&](std::mt19937_64& rng, double rate) -> absl::StatusOr<std::vector<double>> {
    STAGE_ASSIGN_OR_RETURN(const ExpressionLosses l,
                           net->TrainStep(sampler.Draw(job.schedule.batch, latents, rng), rate));
    return std::vector<double>{l.total, l.reconstruction, l.expression_swap, l.view_swap, l.cycle, l.kl};
  };
  auto losses_of = [](const std::vector<double>& v) { return ExpressionLosses{v[0], v[1], v[2], v[3], v[4], v[5]}; };
  if (job.progress) {
    loop.progress = [&](int64_t step, int64_t total, const std::vector<double>& l) {
      return job.progress(step, total, losses_of(l));
    };
  }
  STAGE_ASSIGN_OR_RETURN(const internal::TrainingOutcome outcome, internal::RunTraining(loop));
  result.resumed_from = outcome.resumed_from;
  for (const auto& l : outcome.losses) result.losses.push_back(losses_of(l));
  result.steps = job.schedule.iterations;
  STAGE_RETURN_IF_ERROR(net->Save(result.output_dir + "/expression_vae.pt"));
  STAGE_ASSIGN_OR_RETURN(result.evaluation, EvaluateExpression(*net, d, crops, trained));
  STAGE_RETURN_IF_ERROR(
      WriteFileAtomically(result.output_dir + "/evaluation.json", ExpressionEvaluationJson(result.evaluation) + "\n"));
  return result;
}

absl::Status MappingTrainJob::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("mapping training: no dataset");
  if (mapping.input != 0 || mapping.output != 0) {
    return absl::InvalidArgumentError(
        "mapping training: the mapping's input and output sizes are the VAEs' latents' (leave them 0)");
  }
  LatentMappingOptions sized = mapping;
  sized.input = sized.output = 1;
  STAGE_RETURN_IF_ERROR(sized.Validate());
  if (!(input_noise >= 0 && input_noise <= 2)) {
    return absl::InvalidArgumentError(absl::StrCat("mapping training: input noise ", input_noise, " is not in 0..2"));
  }
  return schedule.Validate();
}

absl::StatusOr<MappingTrainResult> TrainLatentMapping(const MappingTrainJob& job) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  const std::string geometry_run = asset_internal::RunDir(job.geometry_run, job.dataset, "geometry");
  const std::string expression_run = asset_internal::RunDir(job.expression_run, job.dataset, "expression");
  STAGE_ASSIGN_OR_RETURN(DrivenAsset a,
                         LoadDrivenAsset(job.dataset, geometry_run, expression_run, job.mapping.threads));
  const std::vector<std::pair<int64_t, int>> pairs = MappingPairs(a);
  if (pairs.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(job.dataset, ": no training frame seen by a trained camera"));
  }
  STAGE_ASSIGN_OR_RETURN(a.mapping, CreateMapping(a, job.mapping, pairs));
  STAGE_ASSIGN_OR_RETURN(a.expression_latents, EncodeAll(*a.expression, a.crops));
  const LatentMappingOptions& o = a.mapping->options();
  std::vector<std::vector<float>> inputs;
  for (const auto& [f, c] : pairs) inputs.push_back(a.ExpressionOf(f, c));
  std::vector<float> input_mean, input_spread;
  MeanAndSpread(inputs, o.input, &input_mean, &input_spread);

  MappingTrainResult result;
  result.output_dir = asset_internal::RunDir(job.output_dir, job.dataset, "mapping");
  result.parameters = a.mapping->parameter_count();
  result.pairs = static_cast<int64_t>(pairs.size());
  LatentMapping& net = *a.mapping;
  internal::TrainingLoop loop;
  loop.dir = result.output_dir;
  loop.what = "latent mapping";
  STAGE_ASSIGN_OR_RETURN(loop.options, MappingOptionsJson(job, o, asset_internal::DatasetId(a.data.dataset),
                                                          geometry_run, expression_run));
  loop.loss_names = {"total"};
  loop.schedule = job.schedule;
  loop.seed = o.seed;
  loop.save = [&net](const std::string& path) { return net.Save(path); };
  loop.load = [&net](const std::string& path) { return net.Load(path); };
  loop.step = [&](std::mt19937_64& rng, double rate) -> absl::StatusOr<std::vector<double>> {
    const int b = job.schedule.batch;
    std::vector<float> x, y, noise;
    for (int n = 0; n < b; ++n) {
      const size_t i = rng() % pairs.size();
      const int64_t f = pairs[i].first;
      const std::vector<float>& z = inputs[i];
      x.insert(x.end(), z.begin(), z.end());
      const auto target = a.geometry_latents.begin() + static_cast<std::ptrdiff_t>(f * o.output);
      y.insert(y.end(), target, target + o.output);
      for (int k = 0; k < o.input; ++k) {
        noise.push_back(static_cast<float>(job.input_noise) * input_spread[k] * Normal(rng));
      }
    }
    STAGE_ASSIGN_OR_RETURN(const double loss, net.TrainStep(x, y, noise, b, rate));
    return std::vector<double>{loss};
  };
  STAGE_RETURN_IF_ERROR(asset_internal::RunDrivenTraining(loop, job.progress, "mapping.pt", &a, &result));
  return result;
}

absl::StatusOr<DrivenEvaluation> EvaluateDrivenAsset(const std::string& dataset, const std::string& geometry_run,
                                                     const std::string& expression_run, const std::string& mapping_run,
                                                     const std::string& picture, const std::string& finetune_run) {
  const std::string finetune = finetune_run == "none" ? "" : asset_internal::RunDir(finetune_run, dataset, "finetune");
  STAGE_ASSIGN_OR_RETURN(const DrivenAsset a,
                         asset_internal::LoadDriven(dataset, geometry_run, expression_run, mapping_run, finetune, 0));
  if (!picture.empty()) STAGE_RETURN_IF_ERROR(WritePicture(a, picture));
  return EvaluateDriven(a);
}

std::string ExpressionEvaluationJson(const ExpressionEvaluation& e) {
  nlohmann::json j;
  const char* names[3] = {"train", "held_out_block", "held_out_sequence"};
  for (int s = 0; s < 3; ++s) {
    j[names[s]] = {{"reconstruction_trained_cameras", e.reconstruction_trained[s]},
                   {"reconstruction_held_out_cameras", e.reconstruction_held_out[s]},
                   {"view_share", e.view_share[s]}};
  }
  return j.dump();
}

std::string DrivenEvaluationJson(const DrivenEvaluation& e) {
  nlohmann::json j;
  const char* names[3] = {"train", "held_out_block", "held_out_sequence"};
  for (int s = 0; s < 3; ++s) {
    j["autoencoded"][names[s]] = asset_internal::SplitJson(e.autoencoded[s]);
    j["neutral"][names[s]] = asset_internal::SplitJson(e.neutral[s]);
  }
  for (const DrivenEvaluation::Camera& c : e.cameras) {
    nlohmann::json cj = {{"camera", c.id}, {"trained", c.trained}};
    for (int s = 0; s < 3; ++s) cj[names[s]] = asset_internal::SplitJson(c.error[s]);
    j["cameras"].push_back(cj);
  }
  return j.dump();
}

std::string FormatDrivenEvaluation(const DrivenEvaluation& e) {
  std::string out = absl::StrFormat("%-18s %-22s %6s  %-19s %s\n", "split", "driven from", "frames",
                                    "texels rmse / p99", "vertices rmse mm: face / eyes / mouth");
  const char* names[3] = {"train", "held-out blocks", "held-out sequence"};
  auto row = [&](int s, const std::string& what, const SplitError& x) {
    absl::StrAppendFormat(&out, "%-18s %-22s %6d  %7.3f / %7.3f   %7.3f / %7.3f / %7.3f\n", names[s], what, x.frames,
                          x.rmse_mm, x.p99_mm, x.face_mm, x.eyes_mm, x.mouth_mm);
  };
  for (int s = 0; s < 3; ++s) {
    for (const DrivenEvaluation::Camera& c : e.cameras) {
      row(s, absl::StrCat(c.id, c.trained ? " (trained)" : " (HELD OUT)"), c.error[s]);
    }
    row(s, "its map (autoencoded)", e.autoencoded[s]);
    row(s, "neutral frame", e.neutral[s]);
  }
  absl::StrAppend(&out,
                  "(the paper's figures, driven from one held-out view: face 1.516, eyes 1.164, mouth 2.750 mm; its "
                  "goals here: face <= 0.5, eyes <= 0.5, mouth <= 1.0 mm)\n");
  return out;
}

}  // namespace stage::processing
