// Training the neural asset's networks: see asset_train.h.
#include "stage/processing/asset_train.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <optional>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "asset_train_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/face_template.h"
#include "stage/processing/warp_net.h"
#include "training_run.h"

namespace stage::processing {
namespace asset_internal {
namespace {

namespace fs = std::filesystem;
using internal::Normal;
using internal::Uniform;
constexpr double kPi = 3.14159265358979323846;

// Averages each map's valid texels down by `factor` (a texel is valid where any of its sources is).
NetMaps Downsample(const AssetDataset& d, int size) {
  NetMaps out;
  out.size = size;
  const int in = d.geometry_size, k = in / size;
  const size_t texels_in = static_cast<size_t>(in) * in, texels = static_cast<size_t>(size) * size;
  for (int64_t f = 0; f < d.frames(); ++f) {
    std::vector<float> map(3 * texels, 0.f), valid(texels, 0.f);
    for (int y = 0; y < size; ++y) {
      for (int x = 0; x < size; ++x) {
        double sum[3] = {0, 0, 0};
        int n = 0;
        for (int dy = 0; dy < k; ++dy) {
          for (int dx = 0; dx < k; ++dx) {
            const size_t t = static_cast<size_t>(f) * texels_in + static_cast<size_t>(y * k + dy) * in + x * k + dx;
            if (!d.valid[t]) continue;
            for (int c = 0; c < 3; ++c) sum[c] += d.geometry[3 * t + c];
            ++n;
          }
        }
        if (n == 0) continue;
        const size_t t = static_cast<size_t>(y) * size + x;
        for (int c = 0; c < 3; ++c) map[c * texels + t] = static_cast<float>(sum[c] / n);
        valid[t] = 1;
      }
    }
    out.maps.push_back(std::move(map));
    out.valid.push_back(std::move(valid));
  }
  return out;
}

// The training frames' mean map and their RMS spread about it (mm).
void MeanAndScale(const NetMaps& m, const std::vector<int64_t>& train, std::vector<float>* mean, float* scale) {
  const size_t texels = static_cast<size_t>(m.size) * m.size;
  std::vector<double> sum(3 * texels, 0), count(texels, 0);
  for (int64_t f : train) {
    for (size_t t = 0; t < texels; ++t) {
      if (!m.valid[f][t]) continue;
      for (int c = 0; c < 3; ++c) sum[c * texels + t] += m.maps[f][c * texels + t];
      ++count[t];
    }
  }
  mean->assign(3 * texels, 0.f);
  for (size_t t = 0; t < texels; ++t) {
    for (int c = 0; c < 3; ++c)
      (*mean)[c * texels + t] = count[t] > 0 ? static_cast<float>(sum[c * texels + t] / count[t]) : 0.f;
  }
  double se = 0, n = 0;
  for (int64_t f : train) {
    for (size_t t = 0; t < texels; ++t) {
      if (!m.valid[f][t]) continue;
      for (int c = 0; c < 3; ++c) se += std::pow(m.maps[f][c * texels + t] - (*mean)[c * texels + t], 2);
      n += 3;
    }
  }
  *scale = static_cast<float>(std::max(1e-3, std::sqrt(se / std::max(1.0, n))));
}

// A rigid motion about the head's origin: turns about y, x and z and a shift, each uniform in +-rotation_deg and
// +-translation_mm, drawn in that order.
struct RigidMotion {
  Eigen::Matrix3f r;
  Eigen::Vector3f t;
};
RigidMotion DrawRigidMotion(std::mt19937_64& rng, double rotation_deg, double translation_mm) {
  const double deg = kPi / 180;
  RigidMotion m;
  m.r = (Eigen::AngleAxisd(Uniform(rng, rotation_deg) * deg, Eigen::Vector3d::UnitY()) *
         Eigen::AngleAxisd(Uniform(rng, rotation_deg) * deg, Eigen::Vector3d::UnitX()) *
         Eigen::AngleAxisd(Uniform(rng, rotation_deg) * deg, Eigen::Vector3d::UnitZ()))
            .toRotationMatrix()
            .cast<float>();
  for (int c = 0; c < 3; ++c) m.t[c] = static_cast<float>(Uniform(rng, translation_mm));
  return m;
}

// An NCHW map (3 x texels) moved by `motion`, appended to `out`.
void AppendMoved(const std::vector<float>& map, size_t texels, const RigidMotion& motion, std::vector<float>* out) {
  const size_t base = out->size();
  out->resize(base + 3 * texels);
  for (size_t k = 0; k < texels; ++k) {
    const Eigen::Vector3f p = motion.r * Eigen::Vector3f(map[k], map[texels + k], map[2 * texels + k]) + motion.t;
    for (int c = 0; c < 3; ++c) (*out)[base + c * texels + k] = p[c];
  }
}

GeometryBatch DrawBatch(const NetMaps& m, const std::vector<int64_t>& train, const AssetTrainJob& job,
                        const std::vector<float>& region_weights, std::mt19937_64& rng) {
  const int b = job.schedule.batch, s = m.size;
  const size_t texels = static_cast<size_t>(s) * s;
  const int latents = job.geometry.geometry_latent + job.geometry.pose_latent;
  GeometryBatch batch;
  batch.batch = b;
  for (int i = 0; i < b; ++i) {
    const int64_t f = train[static_cast<size_t>(rng() % train.size())];
    const RigidMotion motion = DrawRigidMotion(rng, job.augment_rotation_deg, job.augment_translation_mm);
    const std::vector<float>& map = m.maps[static_cast<size_t>(f)];
    batch.canonical.insert(batch.canonical.end(), map.begin(), map.end());
    AppendMoved(map, texels, motion, &batch.posed);
    const std::vector<float>& valid = m.valid[static_cast<size_t>(f)];
    batch.valid.insert(batch.valid.end(), valid.begin(), valid.end());
    if (!region_weights.empty()) {
      for (size_t t = 0; t < texels; ++t) batch.weight.push_back(valid[t] * region_weights[t]);
    }
    for (int l = 0; l < latents; ++l) batch.noise.push_back(Normal(rng));
  }
  return batch;
}

// What a resume must find the same (every option, the dataset's identity: a hash of its description and frame
// count, so a rebuilt dataset of other frames is not trained on as the old one; and the threads, for bit-identical
// steps).
nlohmann::json OptionsJson(const AssetTrainJob& job, const std::string& dataset_id) {
  const GeometryVaeOptions& g = job.geometry;
  nlohmann::json j = {{"network", "geometry"},
                      {"input_size", g.input_size},
                      {"levels", g.levels},
                      {"base_channels", g.base_channels},
                      {"max_channels", g.max_channels},
                      {"geometry_latent", g.geometry_latent},
                      {"pose_latent", g.pose_latent},
                      {"kl_weight", g.kl_weight},
                      {"seed", g.seed},
                      {"augment_rotation_deg", job.augment_rotation_deg},
                      {"augment_translation_mm", job.augment_translation_mm},
                      {"region_weight", job.region_weight},
                      {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
                      {"dataset_id", dataset_id},
                      {"threads", TorchThreadCount(g.threads)}};
  AddScheduleJson(job.schedule, &j);
  return j;
}

// The 2 x 2 texels a bilinear lookup at `uv` reads in a map of `size` (texel centres at (i + 0.5) / size, row 0 at
// v = 1, clamped): the top-left one and the lookup's fractions past it.
struct BilinearCell {
  int x0, y0;
  double fx, fy;
};
BilinearCell CellAt(const Eigen::Vector2f& uv, int size) {
  const double x = std::clamp(uv.x() * size - 0.5, 0.0, size - 1.0);
  const double y = std::clamp((1 - uv.y()) * size - 0.5, 0.0, size - 1.0);
  const int x0 = std::min(size - 2, static_cast<int>(x)), y0 = std::min(size - 2, static_cast<int>(y));
  return {x0, y0, x - x0, y - y0};
}

}  // namespace

std::optional<Eigen::Vector3d> SampleNchw(const std::vector<float>& map, const std::vector<float>& valid, int size,
                                          const Eigen::Vector2f& uv) {
  const auto [x0, y0, fx, fy] = CellAt(uv, size);
  const size_t texels = static_cast<size_t>(size) * size;
  Eigen::Vector3d p = Eigen::Vector3d::Zero();
  for (int dy = 0; dy < 2; ++dy) {
    for (int dx = 0; dx < 2; ++dx) {
      const size_t t = static_cast<size_t>(y0 + dy) * size + x0 + dx;
      if (!valid[t]) return std::nullopt;
      const double w = (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy);
      for (int c = 0; c < 3; ++c) p[c] += w * map[c * texels + t];
    }
  }
  return p;
}

std::vector<float> RegionWeights(const FaceTemplate& face, int size, double weight) {
  if (weight == 1) return {};
  std::vector<float> w(static_cast<size_t>(size) * size, 1.f);
  for (size_t v = 0; v < face.mesh.uvs.size(); ++v) {
    if (face.regions[v] == FaceRegion::kSkin) continue;
    const BilinearCell cell = CellAt(face.mesh.uvs[v], size);  // SampleNchw's four texels, and the ring about them
    const int x0 = cell.x0, y0 = cell.y0;
    for (int ty = std::max(0, y0 - 1); ty <= std::min(size - 1, y0 + 2); ++ty) {
      for (int tx = std::max(0, x0 - 1); tx <= std::min(size - 1, x0 + 2); ++tx) {
        w[static_cast<size_t>(ty) * size + tx] = static_cast<float>(weight);
      }
    }
  }
  return w;
}

SplitError Error(const NetMaps& m, const FaceTemplate& face, const std::vector<int64_t>& frames,
                 const std::function<std::vector<float>(int64_t)>& recovered) {
  SplitError e;
  std::vector<float> errors;
  const size_t texels = static_cast<size_t>(m.size) * m.size;
  double se = 0, region_se[3] = {0, 0, 0}, region_n[3] = {0, 0, 0};
  const std::vector<float> all_valid(texels, 1.f);
  for (int64_t f : frames) {
    const std::vector<float> r = recovered(f);
    for (size_t t = 0; t < texels; ++t) {
      if (!m.valid[f][t]) continue;
      double d2 = 0;
      for (int c = 0; c < 3; ++c) d2 += std::pow(r[c * texels + t] - m.maps[f][c * texels + t], 2);
      se += d2;
      errors.push_back(static_cast<float>(std::sqrt(d2)));
    }
    // The vertices whose texels the frame's truth holds (a reconstruction's map has holes).
    for (size_t v = 0; v < face.mesh.uvs.size(); ++v) {
      const std::optional<Eigen::Vector3d> truth = SampleNchw(m.maps[f], m.valid[f], m.size, face.mesh.uvs[v]);
      if (!truth) continue;
      const int region = static_cast<int>(face.regions[v]);
      region_se[region] += (*SampleNchw(r, all_valid, m.size, face.mesh.uvs[v]) - *truth).squaredNorm();
      ++region_n[region];
    }
  }
  e.frames = static_cast<int64_t>(frames.size());
  if (errors.empty()) return e;
  e.rmse_mm = std::sqrt(se / static_cast<double>(errors.size()));
  const size_t k = std::min(errors.size() - 1, static_cast<size_t>(0.99 * static_cast<double>(errors.size())));
  std::nth_element(errors.begin(), errors.begin() + static_cast<std::ptrdiff_t>(k), errors.end());
  e.p99_mm = errors[k];
  auto rmse = [&](FaceRegion r) {
    const int i = static_cast<int>(r);
    return region_n[i] > 0 ? std::sqrt(region_se[i] / region_n[i]) : 0.0;
  };
  e.face_mm = rmse(FaceRegion::kSkin);
  e.eyes_mm = rmse(FaceRegion::kEye);
  e.mouth_mm = rmse(FaceRegion::kMouth);
  return e;
}

Eigen::MatrixXf Pca(const NetMaps& m, const std::vector<int64_t>& train, const std::vector<float>& mean, int k) {
  const size_t d = mean.size();
  Eigen::MatrixXd x(static_cast<Eigen::Index>(d), static_cast<Eigen::Index>(train.size()));
  for (size_t i = 0; i < train.size(); ++i) {
    for (size_t j = 0; j < d; ++j) {
      x(static_cast<Eigen::Index>(j), static_cast<Eigen::Index>(i)) = m.maps[train[i]][j] - mean[j];
    }
  }
  const Eigen::MatrixXd gram = x.transpose() * x;
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(gram);
  const Eigen::Index n = gram.cols();
  const double largest = std::max(1e-30, eig.eigenvalues()[n - 1]);
  // At most k components, and none of the data's null space (a direction no training frame spans).
  int kept = 0;
  while (kept < std::min<int>(k, static_cast<int>(n)) && eig.eigenvalues()[n - 1 - kept] > 1e-9 * largest) ++kept;
  Eigen::MatrixXf basis(x.rows(), kept);
  for (int c = 0; c < kept; ++c) {
    const Eigen::Index col = n - 1 - c;  // eigenvalues ascend
    basis.col(c) = ((x * eig.eigenvectors().col(col)) / std::sqrt(eig.eigenvalues()[col])).cast<float>();
  }
  return basis;
}

namespace {

absl::StatusOr<TrainedEvaluation> Evaluate(const GeometryVae& net, const NetMaps& m, const AssetDataset& d,
                                           const std::vector<float>& mean) {
  std::vector<int64_t> split[3];
  for (int64_t f = 0; f < d.frames(); ++f) split[static_cast<int>(d.split[f])].push_back(f);
  const GeometryVaeOptions& o = net.options();
  const Eigen::MatrixXf basis = Pca(m, split[0], mean, o.geometry_latent);
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  TrainedEvaluation e;
  absl::Status failed;
  auto autoencoded = [&](const std::vector<float>& input, int64_t f) {
    auto latents = net.Encode(input, m.valid[f], 1);
    if (!latents.ok()) {
      failed = latents.status();
      return std::vector<float>(mean.size(), 0.f);
    }
    latents->resize(static_cast<size_t>(o.geometry_latent));
    auto map = net.Decode(*latents, 1);
    if (!map.ok()) failed = map.status();
    return map.ok() ? *map : std::vector<float>(mean.size(), 0.f);
  };
  const size_t texels = static_cast<size_t>(m.size) * m.size;
  for (int s = 0; s < 3; ++s) {
    e.vae[s] = Error(m, face, split[s], [&](int64_t f) { return autoencoded(m.maps[f], f); });
    e.vae_moved[s] = Error(m, face, split[s], [&](int64_t f) {
      std::mt19937_64 rng(static_cast<uint64_t>(f));  // each frame its own motion, the same in every run
      std::vector<float> moved;
      AppendMoved(m.maps[f], texels, DrawRigidMotion(rng, kMovedRotationDeg, kMovedTranslationMm), &moved);
      return autoencoded(moved, f);
    });
    e.pca[s] = Error(m, face, split[s], [&](int64_t f) {
      const Eigen::Map<const Eigen::VectorXf> x(m.maps[f].data(), static_cast<Eigen::Index>(mean.size()));
      const Eigen::Map<const Eigen::VectorXf> mu(mean.data(), static_cast<Eigen::Index>(mean.size()));
      const Eigen::VectorXf r = mu + basis * (basis.transpose() * (x - mu));
      return std::vector<float>(r.data(), r.data() + r.size());
    });
    e.neutral[s] = Error(m, face, split[s], [&](int64_t) { return m.maps[0]; });
  }
  if (!failed.ok()) return failed;
  return e;
}

}  // namespace

std::string DatasetId(const AssetDataset& d) {
  const absl::string_view frames(reinterpret_cast<const char*>(d.frame.data()), d.frame.size() * sizeof(int64_t));
  return absl::StrFormat("%016x", Fnv1a64(frames, Fnv1a64(d.description)));
}

std::vector<int64_t> FramesOf(const AssetDataset& d, SampleSplit split) {
  std::vector<int64_t> out;
  for (int64_t f = 0; f < d.frames(); ++f) {
    if (d.split[f] == split) out.push_back(f);
  }
  return out;
}

absl::StatusOr<PreparedData> Prepare(const std::string& path, int size) {
  PreparedData p;
  STAGE_ASSIGN_OR_RETURN(p.dataset, ReadAssetDataset(path));
  if (p.dataset.geometry_size % size != 0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": its maps (", p.dataset.geometry_size,
                                                   " texels across) do not divide into the net's ", size));
  }
  p.train = FramesOf(p.dataset, SampleSplit::kTrain);
  if (p.train.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no training frames"));
  p.maps = Downsample(p.dataset, size);
  MeanAndScale(p.maps, p.train, &p.mean, &p.scale);
  return p;
}

namespace {

// The options a run's trainer.json records, of whichever network.
absl::StatusOr<nlohmann::json> TrainerOptions(const std::string& run_dir) {
  const std::string trainer = run_dir + "/trainer.json";
  std::ifstream in(trainer);
  if (!in) return absl::NotFoundError(absl::StrCat(trainer, ": cannot open (is ", run_dir, " a training run?)"));
  nlohmann::json j = nlohmann::json::parse(in, nullptr, false);
  if (!j.is_object() || !j.contains("options") || !j["options"].is_object()) {
    return absl::InvalidArgumentError(absl::StrCat(trainer, ": not a training run's state"));
  }
  return std::move(j["options"]);
}

}  // namespace

absl::StatusOr<nlohmann::json> RunOptions(const std::string& run_dir, const std::string& network) {
  STAGE_ASSIGN_OR_RETURN(nlohmann::json o, TrainerOptions(run_dir));
  if (o.value("network", "") != network) {
    return absl::InvalidArgumentError(absl::StrCat(run_dir, ": a run of the ",
                                                   o.value("network", nlohmann::json()).dump(), " network, not the ",
                                                   network, " one"));
  }
  return o;
}

absl::Status ReadIntOptions(const std::string& run_dir, const nlohmann::json& o,
                            std::initializer_list<std::pair<const char*, int*>> fields) {
  for (const auto& [name, field] : fields) {
    if (!o.contains(name) || !o[name].is_number_integer()) {
      return absl::InvalidArgumentError(absl::StrCat(run_dir, "/trainer.json: option ", name, " is missing"));
    }
    *field = o[name].get<int>();
  }
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<GeometryVae>> LoadGeometryNet(const std::string& run_dir, int threads) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, RunOptions(run_dir, "geometry"));
  GeometryVaeOptions options;
  options.threads = threads;
  STAGE_RETURN_IF_ERROR(ReadIntOptions(run_dir, o,
                                       {{"input_size", &options.input_size},
                                        {"levels", &options.levels},
                                        {"base_channels", &options.base_channels},
                                        {"max_channels", &options.max_channels},
                                        {"geometry_latent", &options.geometry_latent},
                                        {"pose_latent", &options.pose_latent}}));
  // The normalization is the trained net's (buffers of its weights, loaded below).
  const size_t texels = static_cast<size_t>(options.input_size) * options.input_size;
  STAGE_ASSIGN_OR_RETURN(auto net, GeometryVae::Create(options, std::vector<float>(3 * texels, 0.f), 1.f));
  STAGE_RETURN_IF_ERROR(net->Load(run_dir + "/geometry_vae.pt"));
  return net;
}

absl::StatusOr<std::unique_ptr<GeometryVae>> LoadGeometryRun(const std::string& run_dir, const std::string& dataset,
                                                             PreparedData* data, int threads) {
  STAGE_ASSIGN_OR_RETURN(auto net, LoadGeometryNet(run_dir, threads));
  STAGE_ASSIGN_OR_RETURN(*data, Prepare(dataset, net->options().input_size));
  return net;
}

std::string RunDir(const std::string& dir, const std::string& dataset, const char* name) {
  return dir.empty() ? (fs::path(dataset).parent_path() / name).string() : dir;
}

std::string RunTrainedFrom(const std::string& dir, const std::string& later, const char* name,
                           const std::string& dataset) {
  if (!dir.empty() || later.empty()) return RunDir(dir, dataset, name);
  const absl::StatusOr<nlohmann::json> o = TrainerOptions(later);
  if (!o.ok()) return RunDir(dir, dataset, name);  // reported as the later run is loaded
  const nlohmann::json recorded = o->value(absl::StrCat(name, "_run"), nlohmann::json());
  const nlohmann::json id = o->value(absl::StrCat(name, "_run_id"), nlohmann::json());
  if (recorded.is_string() && id.is_string()) {
    // Only the very run: one trained again since (a copied tree's original) leaves the one beside the dataset.
    const absl::StatusOr<std::string> now = RunId(recorded.get<std::string>());
    if (now.ok() && *now == id.get<std::string>()) return recorded.get<std::string>();
  }
  return RunDir(dir, dataset, name);
}

DrivenRuns ResolveDrivenRuns(const std::string& dataset, const std::string& geometry_run,
                             const std::string& expression_run, const std::string& mapping_run,
                             const std::string& finetune) {
  DrivenRuns r;
  r.mapping = RunTrainedFrom(mapping_run, finetune, "mapping", dataset);
  const std::string& later = finetune.empty() ? r.mapping : finetune;
  r.geometry = RunTrainedFrom(geometry_run, later, "geometry", dataset);
  r.expression = RunTrainedFrom(expression_run, later, "expression", dataset);
  return r;
}

nlohmann::json SplitJson(const SplitError& x) {
  return {{"frames", x.frames},   {"rmse_mm", x.rmse_mm}, {"p99_mm", x.p99_mm},
          {"face_mm", x.face_mm}, {"eyes_mm", x.eyes_mm}, {"mouth_mm", x.mouth_mm}};
}

void AddScheduleJson(const TrainingSchedule& s, nlohmann::json* j) {
  (*j)["iterations"] = s.iterations;
  (*j)["batch"] = s.batch;
  (*j)["learning_rate"] = s.learning_rate;
}

}  // namespace asset_internal

using namespace asset_internal;  // NOLINT(build/namespaces): this file's own helpers

absl::Status TrainingSchedule::Validate() const {
  if (iterations < 1 || iterations > 10'000'000) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: iterations ", iterations, " not in 1..10^7"));
  }
  if (batch < 1 || batch > 1024) return absl::InvalidArgumentError(absl::StrCat("asset training: batch ", batch));
  if (!(learning_rate > 0 && learning_rate <= 1)) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: learning rate ", learning_rate, " not in (0, 1]"));
  }
  if (checkpoint_every < 1) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: checkpoint every ", checkpoint_every, " steps"));
  }
  return absl::OkStatus();
}

absl::Status AssetTrainJob::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("asset training: no dataset");
  STAGE_RETURN_IF_ERROR(geometry.Validate());
  STAGE_RETURN_IF_ERROR(schedule.Validate());
  if (!(augment_rotation_deg >= 0 && augment_rotation_deg <= 90) ||
      !(augment_translation_mm >= 0 && augment_translation_mm <= 200)) {
    return absl::InvalidArgumentError("asset training: augmentation out of range (0..90 deg, 0..200 mm)");
  }
  if (!(region_weight >= 1 && region_weight <= 1000)) {
    return absl::InvalidArgumentError(
        absl::StrCat("asset training: region weight ", region_weight, " is not in 1..1000"));
  }
  return absl::OkStatus();
}

absl::StatusOr<TrainedEvaluation> EvaluateGeometryAsset(const std::string& dataset, const std::string& run_dir) {
  PreparedData data;
  STAGE_ASSIGN_OR_RETURN(auto net, LoadGeometryRun(run_dir, dataset, &data));
  return Evaluate(*net, data.maps, data.dataset, data.mean);
}

absl::StatusOr<AssetTrainResult> TrainGeometryAsset(const AssetTrainJob& job) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  STAGE_ASSIGN_OR_RETURN(const PreparedData data, Prepare(job.dataset, job.geometry.input_size));
  const NetMaps& maps = data.maps;
  const std::vector<int64_t>& train = data.train;
  const std::vector<float>& mean = data.mean;
  const float scale = data.scale;
  const AssetDataset& dataset = data.dataset;

  AssetTrainResult result;
  result.output_dir = RunDir(job.output_dir, job.dataset, "geometry");
  STAGE_ASSIGN_OR_RETURN(auto net, GeometryVae::Create(job.geometry, mean, scale));
  result.parameters = net->parameter_count();
  result.scale_mm = scale;
  internal::TrainingLoop loop;
  loop.dir = result.output_dir;
  loop.what = "geometry VAE";
  loop.options = OptionsJson(job, DatasetId(dataset));
  loop.loss_names = {"total", "canonical", "posed", "kl"};
  loop.schedule = job.schedule;
  loop.seed = job.geometry.seed;
  loop.save = [&net](const std::string& path) { return net->Save(path); };
  loop.load = [&net](const std::string& path) { return net->Load(path); };
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  const std::vector<float> region_weights = RegionWeights(face, maps.size, job.region_weight);
  loop.step = [&](std::mt19937_64& rng, double rate) -> absl::StatusOr<std::vector<double>> {
    STAGE_ASSIGN_OR_RETURN(const GeometryLosses l,
                           net->TrainStep(DrawBatch(maps, train, job, region_weights, rng), rate));
    return std::vector<double>{l.total, l.canonical, l.posed, l.kl};
  };
  auto losses_of = [](const std::vector<double>& v) { return GeometryLosses{v[0], v[1], v[2], v[3]}; };
  if (job.progress) {
    loop.progress = [&](int64_t step, int64_t total, const std::vector<double>& l) {
      return job.progress(step, total, losses_of(l));
    };
  }
  STAGE_ASSIGN_OR_RETURN(const internal::TrainingOutcome outcome, internal::RunTraining(loop));
  result.resumed_from = outcome.resumed_from;
  for (const auto& l : outcome.losses) result.losses.push_back(losses_of(l));
  result.steps = job.schedule.iterations;
  STAGE_RETURN_IF_ERROR(net->Save(result.output_dir + "/geometry_vae.pt"));
  STAGE_RETURN_IF_ERROR(net->ExportTorchScript(result.output_dir + "/geometry_vae.torchscript.pt"));
  STAGE_ASSIGN_OR_RETURN(result.evaluation, Evaluate(*net, maps, dataset, mean));
  STAGE_RETURN_IF_ERROR(
      WriteFileAtomically(result.output_dir + "/evaluation.json", TrainedEvaluationJson(result.evaluation) + "\n"));
  return result;
}

std::string TrainedEvaluationJson(const TrainedEvaluation& e) {
  nlohmann::json j;
  const char* names[3] = {"train", "held_out_block", "held_out_sequence"};
  for (int s = 0; s < 3; ++s) {
    for (auto [model, errors] : {std::pair{"vae", e.vae}, std::pair{"vae_moved", e.vae_moved}, std::pair{"pca", e.pca},
                                 std::pair{"neutral", e.neutral}}) {
      j[names[s]][model] = SplitJson(errors[s]);
    }
  }
  return j.dump();
}

std::string FormatTrainedEvaluation(const TrainedEvaluation& e) {
  std::string out = absl::StrFormat("%-18s %6s  %-9s %-23s %s\n", "split", "frames", "model", "texels rmse / p99 mm",
                                    "vertices rmse mm: face / eyes / mouth");
  const char* names[3] = {"train", "held-out blocks", "held-out sequence"};
  for (int s = 0; s < 3; ++s) {
    for (auto [model, errors] : {std::pair{"VAE", e.vae}, std::pair{"VAE moved", e.vae_moved}, std::pair{"PCA", e.pca},
                                 std::pair{"neutral", e.neutral}}) {
      const SplitError& x = errors[s];
      absl::StrAppendFormat(&out, "%-18s %6d  %-9s %8.3f / %8.3f      %7.3f / %7.3f / %7.3f\n", names[s], x.frames,
                            model, x.rmse_mm, x.p99_mm, x.face_mm, x.eyes_mm, x.mouth_mm);
    }
  }
  absl::StrAppend(&out,
                  "(the paper's figures, driven from one held-out view: face 1.516, eyes 1.164, mouth 2.750 mm; these "
                  "are the geometry encoded and decoded; VAE moved: each map first moved rigidly by up to 5 degrees "
                  "and 5 mm, as a head pose a fit leaves off)\n");
  return out;
}

}  // namespace stage::processing
