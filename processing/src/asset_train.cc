// Training the neural asset's networks: see asset_train.h.
#include "stage/processing/asset_train.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <random>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/face_template.h"
#include "stage/processing/warp_net.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;
constexpr double kPi = 3.14159265358979323846;

// The dataset's maps at the net's resolution, NCHW (3 x S x S each), with their validity (S x S each).
struct NetMaps {
  int size = 0;
  std::vector<std::vector<float>> maps, valid;
};

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

// N(0, 1) from the engine alone (Box-Muller; no distribution object whose cached state a checkpoint would miss).
float Normal(std::mt19937_64& rng) {
  const double u1 = (static_cast<double>(rng() >> 11) + 0.5) * 0x1.0p-53,
               u2 = static_cast<double>(rng() >> 11) * 0x1.0p-53;
  return static_cast<float>(std::sqrt(-2 * std::log(u1)) * std::cos(2 * kPi * u2));
}
double Uniform(std::mt19937_64& rng, double half_range) {
  return half_range * (2 * static_cast<double>(rng() >> 11) * 0x1.0p-53 - 1);
}

GeometryBatch DrawBatch(const NetMaps& m, const std::vector<int64_t>& train, const AssetTrainJob& job,
                        std::mt19937_64& rng) {
  const int b = job.batch, s = m.size;
  const size_t texels = static_cast<size_t>(s) * s;
  const int latents = job.geometry.geometry_latent + job.geometry.pose_latent;
  GeometryBatch batch;
  batch.batch = b;
  for (int i = 0; i < b; ++i) {
    const int64_t f = train[static_cast<size_t>(rng() % train.size())];
    const double deg = kPi / 180;
    const Eigen::Matrix3f r =
        (Eigen::AngleAxisd(Uniform(rng, job.augment_rotation_deg) * deg, Eigen::Vector3d::UnitY()) *
         Eigen::AngleAxisd(Uniform(rng, job.augment_rotation_deg) * deg, Eigen::Vector3d::UnitX()) *
         Eigen::AngleAxisd(Uniform(rng, job.augment_rotation_deg) * deg, Eigen::Vector3d::UnitZ()))
            .toRotationMatrix()
            .cast<float>();
    Eigen::Vector3f t;
    for (int c = 0; c < 3; ++c) t[c] = static_cast<float>(Uniform(rng, job.augment_translation_mm));
    const std::vector<float>& map = m.maps[static_cast<size_t>(f)];
    batch.canonical.insert(batch.canonical.end(), map.begin(), map.end());
    const size_t base = batch.posed.size();
    batch.posed.resize(base + 3 * texels);
    for (size_t k = 0; k < texels; ++k) {
      const Eigen::Vector3f p = r * Eigen::Vector3f(map[k], map[texels + k], map[2 * texels + k]) + t;
      for (int c = 0; c < 3; ++c) batch.posed[base + c * texels + k] = p[c];
    }
    const std::vector<float>& valid = m.valid[static_cast<size_t>(f)];
    batch.valid.insert(batch.valid.end(), valid.begin(), valid.end());
    for (int l = 0; l < latents; ++l) batch.noise.push_back(Normal(rng));
  }
  return batch;
}

// A dataset's identity: FNV-1a of its description (source, take, sizes, sequences, split) and frame numbers.
std::string DatasetId(const AssetDataset& d) {
  const absl::string_view frames(reinterpret_cast<const char*>(d.frame.data()), d.frame.size() * sizeof(int64_t));
  return absl::StrFormat("%016x", Fnv1a64(frames, Fnv1a64(d.description)));
}

// What a resume must find the same (every option, the dataset's identity: a hash of its description and frame
// count, so a rebuilt dataset of other frames is not trained on as the old one; and the threads, for bit-identical
// steps).
nlohmann::json OptionsJson(const AssetTrainJob& job, const std::string& dataset_id) {
  const GeometryVaeOptions& g = job.geometry;
  return {{"network", "geometry"},
          {"input_size", g.input_size},
          {"levels", g.levels},
          {"base_channels", g.base_channels},
          {"max_channels", g.max_channels},
          {"geometry_latent", g.geometry_latent},
          {"pose_latent", g.pose_latent},
          {"kl_weight", g.kl_weight},
          {"seed", g.seed},
          {"iterations", job.iterations},
          {"batch", job.batch},
          {"learning_rate", job.learning_rate},
          {"augment_rotation_deg", job.augment_rotation_deg},
          {"augment_translation_mm", job.augment_translation_mm},
          {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
          {"dataset_id", dataset_id},
          {"threads", TorchThreadCount(g.threads)}};
}

absl::Status WriteLosses(const std::string& dir, const std::vector<GeometryLosses>& losses) {
  std::string csv = "step,total,canonical,posed,kl\n";
  for (size_t i = 0; i < losses.size(); ++i) {
    const GeometryLosses& l = losses[i];
    absl::StrAppendFormat(&csv, "%d,%.17g,%.17g,%.17g,%.17g\n", i + 1, l.total, l.canonical, l.posed, l.kl);
  }
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(dir + "/loss.csv", csv));
  // The curves, log scale, each smoothed over 1 % of the run.
  constexpr int kW = 800, kH = 400, kPad = 40;
  cv::Mat plot(kH, kW, CV_8UC3, cv::Scalar(255, 255, 255));
  if (!losses.empty()) {
    const std::vector<std::pair<double GeometryLosses::*, cv::Scalar>> curves = {
        {&GeometryLosses::total, {0, 0, 0}},
        {&GeometryLosses::canonical, {200, 80, 0}},
        {&GeometryLosses::posed, {0, 140, 0}}};
    double lo = INFINITY, hi = -INFINITY;
    for (const auto& l : losses) {
      for (const auto& [field, colour] : curves) {
        if (l.*field > 0) lo = std::min(lo, std::log10(l.*field)), hi = std::max(hi, std::log10(l.*field));
      }
    }
    if (!(hi > lo)) hi = lo + 1;
    const int window = std::max<int>(1, static_cast<int>(losses.size() / 100));
    for (const auto& [field, colour] : curves) {
      std::vector<cv::Point> points;
      for (size_t i = 0; i < losses.size(); i += static_cast<size_t>(window)) {
        double sum = 0;
        int n = 0;
        for (size_t j = i; j < std::min(losses.size(), i + window); ++j) sum += losses[j].*field, ++n;
        const double v = std::log10(std::max(1e-12, sum / n));
        points.emplace_back(kPad + static_cast<int>((kW - 2 * kPad) * i / std::max<size_t>(1, losses.size() - 1)),
                            kH - kPad - static_cast<int>((kH - 2 * kPad) * (v - lo) / (hi - lo)));
      }
      cv::polylines(plot, points, false, colour, 1, cv::LINE_AA);
    }
    cv::putText(plot, absl::StrFormat("loss (log10 %.2f .. %.2f): total black, canonical blue, posed green", lo, hi),
                {kPad, 25}, cv::FONT_HERSHEY_SIMPLEX, 0.5, {0, 0, 0}, 1, cv::LINE_AA);
    cv::putText(plot, absl::StrCat("step 1 .. ", losses.size()), {kPad, kH - 12}, cv::FONT_HERSHEY_SIMPLEX, 0.5,
                {0, 0, 0}, 1, cv::LINE_AA);
  }
  const std::string tmp = dir + "/loss.tmp.png";
  std::error_code ec;
  if (!cv::imwrite(tmp, plot)) return absl::UnavailableError(absl::StrCat(tmp, ": cannot write"));
  fs::rename(tmp, dir + "/loss.png", ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, "/loss.png: ", ec.message()));
  return absl::OkStatus();
}

absl::StatusOr<std::vector<GeometryLosses>> ReadLosses(const std::string& path, int64_t steps) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": missing (the run's losses)"));
  std::vector<GeometryLosses> out;
  std::string line;
  std::getline(in, line);
  while (static_cast<int64_t>(out.size()) < steps && std::getline(in, line)) {
    GeometryLosses l;
    long long step = 0;
    if (std::sscanf(line.c_str(), "%lld,%lf,%lf,%lf,%lf", &step, &l.total, &l.canonical, &l.posed, &l.kl) != 5) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ": line \"", line, "\" is not step,total,canonical,posed,kl"));
    }
    out.push_back(l);
  }
  if (static_cast<int64_t>(out.size()) != steps) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": holds ", out.size(), " steps, the checkpoint ", steps));
  }
  return out;
}

std::string CheckpointName(int64_t step) { return absl::StrFormat("checkpoint-%06d.pt", step); }

// The run's state at `step`: the net and Adam's state in a file of the step's own (checkpoint-NNNNNN.pt), the losses,
// then trainer.json naming that file (the state counts once it is renamed into place), then the previous checkpoint
// removed. A kill at any point leaves trainer.json naming a whole checkpoint of its own step.
absl::Status SaveCheckpoint(const std::string& dir, const GeometryVae& net, const AssetTrainJob& job,
                            const std::string& dataset_id, int64_t step, const std::mt19937_64& rng,
                            const std::vector<GeometryLosses>& losses, std::string* checkpoint) {
  const std::string name = CheckpointName(step);
  STAGE_RETURN_IF_ERROR(net.Save(dir + "/" + name));
  STAGE_RETURN_IF_ERROR(WriteLosses(dir, losses));
  std::ostringstream state;
  state << rng;
  nlohmann::json j = {
      {"step", step}, {"checkpoint", name}, {"rng", state.str()}, {"options", OptionsJson(job, dataset_id)}};
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(dir + "/trainer.json", j.dump(2) + "\n"));
  if (!checkpoint->empty() && *checkpoint != name) {
    std::error_code ec;
    fs::remove(dir + "/" + *checkpoint, ec);
  }
  *checkpoint = name;
  return absl::OkStatus();
}

// trainer.json read back and checked against the job's options; the step, the checkpoint and the generator's state.
struct TrainerState {
  int64_t step = 0;
  std::string checkpoint;
  std::mt19937_64 rng;
};
// FailedPrecondition names an option the run was trained with otherwise.
absl::StatusOr<TrainerState> ReadTrainerState(const std::string& path, const AssetTrainJob& job,
                                              const std::string& dataset_id) {
  std::ifstream in(path);
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, false);
  if (!j.is_object() || !j.contains("step") || !j["step"].is_number_integer() || !j.contains("rng") ||
      !j["rng"].is_string() || !j.contains("checkpoint") || !j["checkpoint"].is_string() || !j.contains("options") ||
      !j["options"].is_object()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a training run's state"));
  }
  const nlohmann::json mine = OptionsJson(job, dataset_id);  // named: items() of a temporary would dangle
  for (const auto& [key, value] : mine.items()) {
    if (!j["options"].contains(key) || j["options"][key] != value) {
      return absl::FailedPreconditionError(absl::StrCat(path, ": the checkpoint was trained with ", key, " = ",
                                                        j["options"].value(key, nlohmann::json()).dump(), ", not ",
                                                        value.dump()));
    }
  }
  TrainerState t;
  t.step = j["step"].get<int64_t>();
  t.checkpoint = j["checkpoint"].get<std::string>();
  std::istringstream state(j["rng"].get<std::string>());
  state >> t.rng;
  if (state.fail() || t.step < 0 || t.step > job.iterations) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": its step or generator state does not read"));
  }
  return t;
}

// An NCHW map of `size` texels at `uv` (texel centres at (i + 0.5) / size, row 0 at v = 1), bilinear, clamped;
// nullopt where one of the four texels is not valid.
std::optional<Eigen::Vector3d> SampleNchw(const std::vector<float>& map, const std::vector<float>& valid, int size,
                                          const Eigen::Vector2f& uv) {
  const double x = std::clamp(uv.x() * size - 0.5, 0.0, size - 1.0);
  const double y = std::clamp((1 - uv.y()) * size - 0.5, 0.0, size - 1.0);
  const int x0 = std::min(size - 2, static_cast<int>(x)), y0 = std::min(size - 2, static_cast<int>(y));
  const double fx = x - x0, fy = y - y0;
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

// Each split's error of `recovered` maps (frame -> NCHW map) against the truth.
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

// PCA of the training maps about `mean` (components as the columns of the result, orthonormal), from the frames'
// Gram matrix.
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

absl::StatusOr<TrainedEvaluation> Evaluate(const GeometryVae& net, const NetMaps& m, const AssetDataset& d,
                                           const std::vector<float>& mean) {
  std::vector<int64_t> split[3];
  for (int64_t f = 0; f < d.frames(); ++f) split[static_cast<int>(d.split[f])].push_back(f);
  const GeometryVaeOptions& o = net.options();
  const Eigen::MatrixXf basis = Pca(m, split[0], mean, o.geometry_latent);
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  TrainedEvaluation e;
  absl::Status failed;
  for (int s = 0; s < 3; ++s) {
    e.vae[s] = Error(m, face, split[s], [&](int64_t f) {
      auto latents = net.Encode(m.maps[f], m.valid[f], 1);
      if (!latents.ok()) {
        failed = latents.status();
        return std::vector<float>(mean.size(), 0.f);
      }
      latents->resize(static_cast<size_t>(o.geometry_latent));
      auto map = net.Decode(*latents, 1);
      if (!map.ok()) failed = map.status();
      return map.ok() ? *map : std::vector<float>(mean.size(), 0.f);
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

absl::Status AssetTrainJob::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("asset training: no dataset");
  STAGE_RETURN_IF_ERROR(geometry.Validate());
  if (iterations < 1 || iterations > 10'000'000) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: iterations ", iterations, " not in 1..10^7"));
  }
  if (batch < 1 || batch > 1024) return absl::InvalidArgumentError(absl::StrCat("asset training: batch ", batch));
  if (!(learning_rate > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: learning rate ", learning_rate));
  }
  if (checkpoint_every < 1) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: checkpoint every ", checkpoint_every, " steps"));
  }
  if (!(augment_rotation_deg >= 0 && augment_rotation_deg <= 90) ||
      !(augment_translation_mm >= 0 && augment_translation_mm <= 200)) {
    return absl::InvalidArgumentError("asset training: augmentation out of range (0..90 deg, 0..200 mm)");
  }
  return absl::OkStatus();
}

namespace {

// A dataset read for a net of input `size`: its maps at that size, the training frames, their mean and spread.
struct PreparedData {
  AssetDataset dataset;
  NetMaps maps;
  std::vector<int64_t> train;
  std::vector<float> mean;
  float scale = 0;
};

absl::StatusOr<PreparedData> Prepare(const std::string& path, int size) {
  PreparedData p;
  STAGE_ASSIGN_OR_RETURN(p.dataset, ReadAssetDataset(path));
  if (p.dataset.geometry_size % size != 0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": its maps (", p.dataset.geometry_size,
                                                   " texels across) do not divide into the net's ", size));
  }
  for (int64_t f = 0; f < p.dataset.frames(); ++f) {
    if (p.dataset.split[f] == SampleSplit::kTrain) p.train.push_back(f);
  }
  if (p.train.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no training frames"));
  p.maps = Downsample(p.dataset, size);
  MeanAndScale(p.maps, p.train, &p.mean, &p.scale);
  return p;
}

}  // namespace

absl::StatusOr<TrainedEvaluation> EvaluateGeometryAsset(const std::string& dataset, const std::string& run_dir) {
  const std::string trainer = run_dir + "/trainer.json";
  std::ifstream in(trainer);
  if (!in) return absl::NotFoundError(absl::StrCat(trainer, ": cannot open (is ", run_dir, " a training run?)"));
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, false);
  if (!j.is_object() || !j.contains("options") || !j["options"].is_object()) {
    return absl::InvalidArgumentError(absl::StrCat(trainer, ": not a training run's state"));
  }
  const nlohmann::json& o = j["options"];
  GeometryVaeOptions options;
  try {
    options.input_size = o.at("input_size").get<int>();
    options.levels = o.at("levels").get<int>();
    options.base_channels = o.at("base_channels").get<int>();
    options.max_channels = o.at("max_channels").get<int>();
    options.geometry_latent = o.at("geometry_latent").get<int>();
    options.pose_latent = o.at("pose_latent").get<int>();
  } catch (const nlohmann::json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(trainer, ": options: ", e.what()));
  }
  STAGE_ASSIGN_OR_RETURN(const PreparedData data, Prepare(dataset, options.input_size));
  STAGE_ASSIGN_OR_RETURN(auto net, GeometryVae::Create(options, data.mean, data.scale));
  STAGE_RETURN_IF_ERROR(net->Load(run_dir + "/geometry_vae.pt"));
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
  result.output_dir =
      job.output_dir.empty() ? (fs::path(job.dataset).parent_path() / "geometry").string() : job.output_dir;
  std::error_code ec;
  fs::create_directories(result.output_dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(result.output_dir, ": ", ec.message()));
  STAGE_ASSIGN_OR_RETURN(auto net, GeometryVae::Create(job.geometry, mean, scale));
  result.parameters = net->parameter_count();
  result.scale_mm = scale;
  std::mt19937_64 rng(job.geometry.seed ^ 0xa55e7ull);
  const std::string trainer = result.output_dir + "/trainer.json";
  const std::string dataset_id = DatasetId(dataset);
  std::string checkpoint;
  if (job.resume && fs::exists(trainer)) {
    absl::StatusOr<TrainerState> state = ReadTrainerState(trainer, job, dataset_id);
    if (absl::IsFailedPrecondition(state.status()) && job.restart_if_different) {
      Logger("processing.asset")->info("{} (starting anew)", state.status().message());
    } else if (!state.ok()) {
      return absl::Status(state.status().code(), absl::StrCat(state.status().message(),
                                                              " (start anew: without resuming, or another directory)"));
    } else {
      STAGE_RETURN_IF_ERROR(net->Load(result.output_dir + "/" + state->checkpoint));
      rng = state->rng;
      checkpoint = state->checkpoint;
      result.resumed_from = state->step;
      STAGE_ASSIGN_OR_RETURN(result.losses, ReadLosses(result.output_dir + "/loss.csv", result.resumed_from));
    }
  }
  const int64_t slow_from = static_cast<int64_t>(0.7 * job.iterations);
  for (int64_t step = result.resumed_from; step < job.iterations; ++step) {
    const GeometryBatch batch = DrawBatch(maps, train, job, rng);
    STAGE_ASSIGN_OR_RETURN(const GeometryLosses losses,
                           net->TrainStep(batch, step < slow_from ? job.learning_rate : job.learning_rate / 5));
    result.losses.push_back(losses);
    const bool last = step + 1 == job.iterations;
    if ((step + 1) % job.checkpoint_every == 0 || last) {
      STAGE_RETURN_IF_ERROR(
          SaveCheckpoint(result.output_dir, *net, job, dataset_id, step + 1, rng, result.losses, &checkpoint));
    }
    if (job.progress && !job.progress(step + 1, job.iterations, losses)) {
      return absl::CancelledError(absl::StrCat("asset training stopped at step ", step + 1,
                                               " (checkpoint: ", result.output_dir, "/", checkpoint, ")"));
    }
  }
  result.steps = job.iterations;
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
    for (auto [model, errors] : {std::pair{"vae", e.vae}, std::pair{"pca", e.pca}, std::pair{"neutral", e.neutral}}) {
      j[names[s]][model] = {{"frames", errors[s].frames},   {"rmse_mm", errors[s].rmse_mm},
                            {"p99_mm", errors[s].p99_mm},   {"face_mm", errors[s].face_mm},
                            {"eyes_mm", errors[s].eyes_mm}, {"mouth_mm", errors[s].mouth_mm}};
    }
  }
  return j.dump();
}

std::string FormatTrainedEvaluation(const TrainedEvaluation& e) {
  std::string out = absl::StrFormat("%-18s %6s  %-8s %-23s %s\n", "split", "frames", "model", "texels rmse / p99 mm",
                                    "vertices rmse mm: face / eyes / mouth");
  const char* names[3] = {"train", "held-out blocks", "held-out sequence"};
  for (int s = 0; s < 3; ++s) {
    for (auto [model, errors] : {std::pair{"VAE", e.vae}, std::pair{"PCA", e.pca}, std::pair{"neutral", e.neutral}}) {
      const SplitError& x = errors[s];
      absl::StrAppendFormat(&out, "%-18s %6d  %-8s %8.3f / %8.3f      %7.3f / %7.3f / %7.3f\n", names[s], x.frames,
                            model, x.rmse_mm, x.p99_mm, x.face_mm, x.eyes_mm, x.mouth_mm);
    }
  }
  absl::StrAppend(&out,
                  "(the paper's figures, driven from one held-out view: face 1.516, eyes 1.164, mouth 2.750 mm; these "
                  "are the geometry encoded and decoded)\n");
  return out;
}

}  // namespace stage::processing
