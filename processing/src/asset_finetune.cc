// The neural asset's third training stage: the driving path (the expression encoder and the mapping) fine-tuned on the
// frames' geometry latents, and the loading of such a run (see asset_train.h's FineTuneDrivingAsset).
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <random>

#include "absl/strings/str_cat.h"
#include "asset_train_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/asset_train.h"
#include "stage/processing/face_template.h"
#include "stage/processing/warp_net.h"
#include "training_run.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;
using asset_internal::DrivenAsset;
using internal::Normal;
using internal::Uniform;

constexpr double kPi = 3.14159265358979323846;

// `in` (size x size, 0..1) jittered into `out` as FineTuneJob's bounds say: sampled bilinearly through a scale, a
// turn and a shift about the centre (0 outside), times a gain, plus noise; every draw from `rng`.
void Jitter(const FineTuneJob& job, const float* in, int size, std::mt19937_64& rng, float* out) {
  const double scale = 1 + Uniform(rng, job.jitter_scale);
  const double angle = Uniform(rng, job.jitter_rotation_deg) * kPi / 180;
  const double sx = Uniform(rng, job.jitter_shift) * size, sy = Uniform(rng, job.jitter_shift) * size;
  const double gain = 1 + Uniform(rng, job.jitter_gain);
  // Output pixel p samples the input at centre + R^-1 (p - centre - shift) / scale.
  const double c = std::cos(angle) / scale, s = std::sin(angle) / scale, mid = 0.5 * (size - 1);
  auto at = [&](int x, int y) {
    return x < 0 || y < 0 || x >= size || y >= size ? 0.f : in[static_cast<size_t>(y) * size + x];
  };
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double dx = x - mid - sx, dy = y - mid - sy;
      const double u = mid + c * dx + s * dy, v = mid - s * dx + c * dy;
      const int x0 = static_cast<int>(std::floor(u)), y0 = static_cast<int>(std::floor(v));
      const float fx = static_cast<float>(u - x0), fy = static_cast<float>(v - y0);
      const float value = (at(x0, y0) * (1 - fx) + at(x0 + 1, y0) * fx) * (1 - fy) +
                          (at(x0, y0 + 1) * (1 - fx) + at(x0 + 1, y0 + 1) * fx) * fy;
      const float noise = job.jitter_noise > 0 ? static_cast<float>(job.jitter_noise) * Normal(rng) : 0.f;
      out[static_cast<size_t>(y) * size + x] = std::clamp(static_cast<float>(gain) * value + noise, 0.f, 1.f);
    }
  }
}

absl::StatusOr<nlohmann::json> FineTuneOptionsJson(const FineTuneJob& job, const DrivenAsset& a,
                                                   const std::string& geometry_run, const std::string& expression_run,
                                                   const std::string& mapping_run) {
  nlohmann::json j = {{"network", "finetune"},
                      {"train_encoder", job.driving.train_encoder},
                      {"jitter_scale", job.jitter_scale},
                      {"jitter_rotation_deg", job.jitter_rotation_deg},
                      {"jitter_shift", job.jitter_shift},
                      {"jitter_gain", job.jitter_gain},
                      {"jitter_noise", job.jitter_noise},
                      {"map_loss_region_weight", job.map_loss_region_weight},
                      {"seed", job.seed},
                      {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
                      {"dataset_id", asset_internal::DatasetId(a.data.dataset)},
                      {"threads", TorchThreadCount(job.driving.threads)}};
  STAGE_RETURN_IF_ERROR(asset_internal::AddRunIdentities(
      {{"geometry", geometry_run}, {"expression", expression_run}, {"mapping", mapping_run}}, &j));
  asset_internal::AddScheduleJson(job.schedule, &j);
  return j;
}

bool InRange(double v, double high) { return v >= 0 && v <= high; }

// The map loss's texel weights: 0 where no training frame holds the texel, the region weights elsewhere.
std::vector<float> MapLossWeights(const asset_internal::PreparedData& data, const FaceTemplate& face, double weight) {
  std::vector<float> w = asset_internal::RegionWeights(face, data.maps.size, weight);
  if (w.empty()) w.assign(static_cast<size_t>(data.maps.size) * data.maps.size, 1.f);
  for (size_t t = 0; t < w.size(); ++t) {
    bool held = false;
    for (int64_t f : data.train) held = held || data.maps.valid[static_cast<size_t>(f)][t] > 0;
    if (!held) w[t] = 0;
  }
  return w;
}

// The step a run's trainer.json says it reached, and its options' iterations (-1 each where unreadable).
std::pair<int64_t, int64_t> StepsOf(const std::string& run_dir) {
  std::ifstream in(run_dir + "/trainer.json");
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, false);
  if (!j.is_object() || !j.contains("step") || !j["step"].is_number_integer() || !j.contains("options")) {
    return {-1, -1};
  }
  return {j["step"].get<int64_t>(), j["options"].value("iterations", int64_t{-1})};
}

}  // namespace

namespace asset_internal {

absl::StatusOr<std::unique_ptr<DrivingNet>> LoadDrivingNet(const std::string& run_dir, const std::string& geometry_run,
                                                           const std::string& expression_run,
                                                           const std::string& mapping_run,
                                                           const ExpressionVae& expression,
                                                           const LatentMapping& mapping, int threads) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, RunOptions(run_dir, "finetune"));
  STAGE_RETURN_IF_ERROR(
      CheckTrainedFrom(run_dir, o, "fine-tuned",
                       {{"geometry", geometry_run}, {"expression", expression_run}, {"mapping", mapping_run}}));
  // A run started again and stopped part way keeps the last finished run's net beside its own state: not its own.
  if (const auto [step, iterations] = StepsOf(run_dir); step != iterations) {
    return absl::FailedPreconditionError(absl::StrCat(run_dir, ": stopped at step ", step, " of ", iterations,
                                                      " (resume it with --resume, or name another run)"));
  }
  if (!o.contains("train_encoder") || !o["train_encoder"].is_boolean()) {
    return absl::InvalidArgumentError(absl::StrCat(run_dir, "/trainer.json: option train_encoder is missing"));
  }
  DrivingNetOptions options{.train_encoder = o["train_encoder"].get<bool>(), .threads = threads};
  STAGE_ASSIGN_OR_RETURN(auto net, DrivingNet::Create(expression, mapping, options));
  STAGE_RETURN_IF_ERROR(net->Load(run_dir + "/driving_net.pt"));
  return net;
}

std::string FineTuneRun(const std::string& run, const std::string& dataset) {
  if (run == "none") return "";
  if (!run.empty()) return run;
  const std::string dir = RunDir("", dataset, "finetune");
  if (!fs::exists(dir + "/driving_net.pt")) return "";
  return dir;  // LoadDrivingNet refuses it, naming why, if it stopped part way
}

}  // namespace asset_internal

absl::Status FineTuneJob::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("fine-tuning: ", what)); };
  if (dataset.empty()) return bad("no dataset");
  STAGE_RETURN_IF_ERROR(driving.Validate());
  for (const auto& [name, v, high] :
       {std::tuple{"jitter_scale", jitter_scale, 0.5}, std::tuple{"jitter_rotation_deg", jitter_rotation_deg, 45.0},
        std::tuple{"jitter_shift", jitter_shift, 0.5}, std::tuple{"jitter_gain", jitter_gain, 0.9},
        std::tuple{"jitter_noise", jitter_noise, 0.5}}) {
    if (!InRange(v, high)) return bad(absl::StrCat(name, " ", v, " is not in 0..", high));
  }
  if (map_loss_region_weight != 0 && !(map_loss_region_weight >= 1 && map_loss_region_weight <= 1000)) {
    return bad(absl::StrCat("map loss region weight ", map_loss_region_weight, " is neither 0 nor in 1..1000"));
  }
  return schedule.Validate();
}

absl::StatusOr<MappingTrainResult> FineTuneDrivingAsset(const FineTuneJob& job) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  const asset_internal::DrivenRuns runs =
      asset_internal::ResolveDrivenRuns(job.dataset, job.geometry_run, job.expression_run, job.mapping_run, "");
  const int threads = job.driving.threads;
  STAGE_ASSIGN_OR_RETURN(DrivenAsset a,
                         asset_internal::LoadDrivenAsset(job.dataset, runs.geometry, runs.expression, threads));
  STAGE_ASSIGN_OR_RETURN(a.mapping,
                         asset_internal::LoadMappingNet(runs.mapping, a.ExpressionSize(), a.GeometrySize(), threads));
  {
    STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, asset_internal::RunOptions(runs.mapping, "mapping"));
    STAGE_RETURN_IF_ERROR(asset_internal::CheckTrainedFrom(
        runs.mapping, o, "the mapping was trained", {{"geometry", runs.geometry}, {"expression", runs.expression}}));
  }
  const std::vector<std::pair<int64_t, int>> pairs = asset_internal::MappingPairs(a);
  if (pairs.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(job.dataset, ": no training frame seen by a trained camera"));
  }
  STAGE_ASSIGN_OR_RETURN(a.driver, DrivingNet::Create(*a.expression, *a.mapping, job.driving));
  if (job.map_loss_region_weight != 0) {
    STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
    STAGE_RETURN_IF_ERROR(a.driver->UseMapLoss(*a.geometry, MapLossWeights(a.data, face, job.map_loss_region_weight)));
  }
  MappingTrainResult result;
  result.output_dir = asset_internal::RunDir(job.output_dir, job.dataset, "finetune");
  result.parameters = a.driver->trained_parameters();
  result.pairs = static_cast<int64_t>(pairs.size());
  DrivingNet& net = *a.driver;
  internal::TrainingLoop loop;
  loop.dir = result.output_dir;
  loop.what = "driving net";
  STAGE_ASSIGN_OR_RETURN(loop.options, FineTuneOptionsJson(job, a, runs.geometry, runs.expression, runs.mapping));
  loop.loss_names = {"total"};
  loop.schedule = job.schedule;
  loop.seed = job.seed;
  loop.save = [&net](const std::string& path) { return net.Save(path); };
  loop.load = [&net](const std::string& path) { return net.Load(path); };
  const int g = a.GeometrySize(), size = a.crops.size;
  loop.step = [&](std::mt19937_64& rng, double rate) -> absl::StatusOr<std::vector<double>> {
    const int b = job.schedule.batch;
    std::vector<float> images(static_cast<size_t>(b) * a.crops.Pixels()), targets;
    for (int n = 0; n < b; ++n) {
      const auto [f, c] = pairs[rng() % pairs.size()];
      Jitter(job, a.crops.At(f, c), size, rng, images.data() + n * a.crops.Pixels());
      const auto target = a.geometry_latents.begin() + static_cast<std::ptrdiff_t>(f * g);
      targets.insert(targets.end(), target, target + g);
    }
    STAGE_ASSIGN_OR_RETURN(const double loss, net.TrainStep(images, targets, b, rate));
    return std::vector<double>{loss};
  };
  STAGE_RETURN_IF_ERROR(asset_internal::RunDrivenTraining(loop, job.progress, "driving_net.pt", &a, &result));
  return result;
}

}  // namespace stage::processing
