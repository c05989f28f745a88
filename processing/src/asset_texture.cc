// The texture VAE's training and evaluation: see asset_train.h (TrainTextureAsset). Torch-free: the net is reached
// through asset_net.h.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "asset_train_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/common/uv_raster.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/asset_train.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"
#include "stage/processing/warp_net.h"
#include "training_run.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;
using asset_internal::NetMaps;
using asset_internal::PreparedData;

// A dataset's textures at the net's size: each frame's averaged down (a texel valid where any of its sources is),
// NCHW (C x S x S) with its validity (S x S), the training frames, their mean and each channel's spread about it.
struct PreparedTextures {
  AssetDataset dataset;
  NetMaps maps;
  std::vector<int64_t> train;
  std::vector<float> mean, scale;
};

NetMaps DownsampleTextures(const AssetDataset& d, int size) {
  NetMaps out;
  out.size = size;
  const size_t texels_in = static_cast<size_t>(d.texture_size) * d.texture_size;
  for (int64_t f = 0; f < d.frames(); ++f) {
    std::vector<float> map, valid;
    asset_internal::DownsampleTextureMap(&d.textures[static_cast<size_t>(f) * texels_in * kTextureChannels],
                                         &d.texture_valid[static_cast<size_t>(f) * texels_in], d.texture_size, size,
                                         &map, &valid);
    out.maps.push_back(std::move(map));
    out.valid.push_back(std::move(valid));
  }
  return out;
}

absl::StatusOr<PreparedTextures> PrepareTextures(const std::string& path, int size) {
  PreparedTextures p;
  STAGE_ASSIGN_OR_RETURN(p.dataset, ReadAssetDataset(path));
  const AssetDataset& d = p.dataset;
  if (d.texture_size == 0) {
    return absl::FailedPreconditionError(
        absl::StrCat(path,
                     ": the dataset holds no textures (build it from a truth rendered with --uv-textures, or "
                     "after `stage-process textures`)"));
  }
  if (d.texture_size % size != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": its textures (", d.texture_size, " texels across) do not divide into the net's ", size));
  }
  p.train = asset_internal::FramesOf(d, SampleSplit::kTrain);
  if (p.train.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no training frames"));
  p.maps = DownsampleTextures(d, size);
  const size_t texels = static_cast<size_t>(size) * size;
  std::vector<double> sum(kTextureChannels * texels, 0), count(texels, 0);
  for (int64_t f : p.train) {
    for (size_t t = 0; t < texels; ++t) {
      if (!p.maps.valid[f][t]) continue;
      for (int c = 0; c < kTextureChannels; ++c) sum[c * texels + t] += p.maps.maps[f][c * texels + t];
      ++count[t];
    }
  }
  p.mean.assign(kTextureChannels * texels, 0.f);
  for (size_t t = 0; t < texels; ++t) {
    for (int c = 0; c < kTextureChannels; ++c) {
      if (count[t] > 0) p.mean[c * texels + t] = static_cast<float>(sum[c * texels + t] / count[t]);
    }
  }
  std::vector<double> se(kTextureChannels, 0);
  double n = 0;
  for (int64_t f : p.train) {
    for (size_t t = 0; t < texels; ++t) {
      if (!p.maps.valid[f][t]) continue;
      for (int c = 0; c < kTextureChannels; ++c) {
        se[c] += std::pow(p.maps.maps[f][c * texels + t] - p.mean[c * texels + t], 2);
      }
      ++n;
    }
  }
  // A channel that never changes (a material the expressions leave alone) gets a floor, not a division by zero.
  for (int c = 0; c < kTextureChannels; ++c) {
    p.scale.push_back(static_cast<float>(std::max(1e-4, std::sqrt(se[c] / std::max(1.0, n)))));
  }
  return p;
}

// The skin's texels at `size`: those a triangle of the template covers whose corners are all skin.
std::vector<uint8_t> SkinMask(const FaceTemplate& face, int size) {
  const std::vector<UvTexel> texels = RasterizeUv(face.mesh, size, /*part=*/-1);
  std::vector<uint8_t> skin(texels.size(), 0);
  for (size_t t = 0; t < texels.size(); ++t) {
    if (!texels[t].covered()) continue;
    const auto& tri = face.mesh.triangles[static_cast<size_t>(texels[t].triangle)];
    skin[t] = std::all_of(tri.begin(), tri.end(), [&](int32_t v) { return face.regions[v] == FaceRegion::kSkin; });
  }
  return skin;
}

// Linear albedo to 0..255 levels of its sRGB encoding.
double SrgbLevels(double linear) {
  const double x = std::clamp(linear, 0.0, 1.0);
  return 255 * (x <= 0.0031308 ? 12.92 * x : 1.055 * std::pow(x, 1 / 2.4) - 0.055);
}

TextureSplitError TextureError(const NetMaps& m, const std::vector<uint8_t>& skin, const std::vector<int64_t>& frames,
                               const std::function<std::vector<float>(int64_t)>& recovered) {
  TextureSplitError e;
  e.frames = static_cast<int64_t>(frames.size());
  const size_t texels = static_cast<size_t>(m.size) * m.size;
  double albedo_se = 0, angle = 0, specular = 0, n = 0, ns = 0;
  for (int64_t f : frames) {
    const std::vector<float> r = recovered(f);
    const std::vector<float>& truth = m.maps[f];
    for (size_t t = 0; t < texels; ++t) {
      if (!skin[t] || !m.valid[f][t]) continue;
      for (int c = 0; c < 3; ++c) {
        albedo_se += std::pow(SrgbLevels(r[c * texels + t]) - SrgbLevels(truth[c * texels + t]), 2);
      }
      const Eigen::Vector3d a(r[4 * texels + t], r[5 * texels + t], r[6 * texels + t]);
      const Eigen::Vector3d b(truth[4 * texels + t], truth[5 * texels + t], truth[6 * texels + t]);
      if (a.norm() > 0 && b.norm() > 0) {
        angle += std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) * 180 / M_PI;
      }
      ++n;
      if (truth[3 * texels + t] > 0) {
        specular += std::abs(r[3 * texels + t] / truth[3 * texels + t] - 1);
        ++ns;
      }
    }
  }
  if (n > 0) {
    e.albedo_levels = std::sqrt(albedo_se / (3 * n));
    e.normal_deg = angle / n;
  }
  if (ns > 0) e.specular_relative = specular / ns;
  return e;
}

absl::StatusOr<TextureEvaluation> Evaluate(const TextureVae& net, const PreparedTextures& p) {
  std::vector<int64_t> split[3];
  for (int64_t f = 0; f < p.dataset.frames(); ++f) split[static_cast<int>(p.dataset.split[f])].push_back(f);
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  const std::vector<uint8_t> skin = SkinMask(face, p.maps.size);
  const Eigen::MatrixXf basis = asset_internal::Pca(p.maps, p.train, p.mean, net.options().texture_latent);
  const Eigen::Map<const Eigen::VectorXf> mu(p.mean.data(), static_cast<Eigen::Index>(p.mean.size()));
  TextureEvaluation e;
  absl::Status failed;
  for (int s = 0; s < 3; ++s) {
    e.vae[s] = TextureError(p.maps, skin, split[s], [&](int64_t f) {
      absl::StatusOr<std::vector<float>> out = net.Encode(p.maps.maps[f], p.maps.valid[f], 1);
      if (out.ok()) out = net.Decode(*out, 1);
      if (!out.ok()) failed = out.status();
      return out.ok() ? *out : p.mean;
    });
    e.pca[s] = TextureError(p.maps, skin, split[s], [&](int64_t f) {
      // The texels a frame does not hold are the mean's.
      Eigen::VectorXf x = Eigen::Map<const Eigen::VectorXf>(p.maps.maps[f].data(), mu.size());
      const size_t texels = p.maps.valid[f].size();
      for (Eigen::Index i = 0; i < x.size(); ++i) {
        if (!p.maps.valid[f][static_cast<size_t>(i) % texels]) x[i] = mu[i];
      }
      const Eigen::VectorXf r = mu + basis * (basis.transpose() * (x - mu));
      return std::vector<float>(r.data(), r.data() + r.size());
    });
    e.neutral[s] = TextureError(p.maps, skin, split[s], [&](int64_t) { return p.maps.maps[0]; });
  }
  if (!failed.ok()) return failed;
  return e;
}

TextureBatch DrawBatch(const PreparedTextures& p, const TextureTrainJob& job, std::mt19937_64& rng) {
  TextureBatch batch;
  batch.batch = job.schedule.batch;
  for (int i = 0; i < batch.batch; ++i) {
    const int64_t f = p.train[static_cast<size_t>(rng() % p.train.size())];
    batch.textures.insert(batch.textures.end(), p.maps.maps[f].begin(), p.maps.maps[f].end());
    batch.valid.insert(batch.valid.end(), p.maps.valid[f].begin(), p.maps.valid[f].end());
    for (int l = 0; l < job.texture.texture_latent; ++l) batch.noise.push_back(internal::Normal(rng));
  }
  return batch;
}

// Each channel's RMS about zero over the training frames' valid texels (the direct textures' spread).
std::vector<float> DirectScale(const PreparedTextures& p) {
  const size_t texels = static_cast<size_t>(p.maps.size) * p.maps.size;
  std::vector<double> ss(kTextureChannels, 0);
  double n = 0;
  for (int64_t f : p.train) {
    for (size_t t = 0; t < texels; ++t) {
      if (!p.maps.valid[f][t]) continue;
      for (int c = 0; c < kTextureChannels; ++c) ss[c] += std::pow(p.maps.maps[f][c * texels + t], 2);
      ++n;
    }
  }
  std::vector<float> scale;
  for (int c = 0; c < kTextureChannels; ++c) {
    scale.push_back(static_cast<float>(std::max(1e-4, std::sqrt(ss[c] / std::max(1.0, n)))));
  }
  return scale;
}

nlohmann::json OptionsJson(const TextureTrainJob& job, const std::string& dataset_id) {
  const TextureVaeOptions& t = job.texture;
  nlohmann::json j = {{"network", "texture"},
                      {"input_size", t.input_size},
                      {"levels", t.levels},
                      {"base_channels", t.base_channels},
                      {"max_channels", t.max_channels},
                      {"channels", t.channels},
                      {"texture_latent", t.texture_latent},
                      {"direct", job.direct},
                      {"kl_weight", t.kl_weight},
                      {"seed", t.seed},
                      {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
                      {"dataset_id", dataset_id},
                      {"threads", TorchThreadCount(t.threads)}};
  asset_internal::AddScheduleJson(job.schedule, &j);
  return j;
}

}  // namespace

namespace asset_internal {

absl::StatusOr<std::unique_ptr<TextureVae>> LoadTextureNet(const std::string& run_dir, int threads) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, asset_internal::RunOptions(run_dir, "texture"));
  TextureVaeOptions options;
  options.threads = threads;
  STAGE_RETURN_IF_ERROR(asset_internal::ReadIntOptions(run_dir, o,
                                                       {{"input_size", &options.input_size},
                                                        {"levels", &options.levels},
                                                        {"base_channels", &options.base_channels},
                                                        {"max_channels", &options.max_channels},
                                                        {"channels", &options.channels},
                                                        {"texture_latent", &options.texture_latent}}));
  // The normalization is the trained net's (buffers of its weights, loaded below).
  const size_t texels = static_cast<size_t>(options.input_size) * options.input_size;
  STAGE_ASSIGN_OR_RETURN(auto net, TextureVae::Create(options, std::vector<float>(options.channels * texels, 0.f),
                                                      std::vector<float>(options.channels, 1.f)));
  STAGE_RETURN_IF_ERROR(net->Load(run_dir + "/texture_vae.pt"));
  return net;
}

absl::StatusOr<std::unique_ptr<LatentMapping>> LoadTextureMappingNet(const std::string& run_dir,
                                                                     const std::string& geometry_run,
                                                                     const std::string& texture_run,
                                                                     int geometry_latent, int texture_latent,
                                                                     int threads) {
  STAGE_ASSIGN_OR_RETURN(const nlohmann::json o, RunOptions(run_dir, "texture_mapping"));
  STAGE_RETURN_IF_ERROR(
      CheckTrainedFrom(run_dir, o, "texture mapping trained", {{"geometry", geometry_run}, {"texture", texture_run}}));
  return LoadMappingNet(run_dir, geometry_latent, texture_latent, threads, "texture_mapping");
}

void DownsampleTextureMap(const float* maps, const uint8_t* valid, int in, int size, std::vector<float>* out,
                          std::vector<float>* out_valid) {
  const int k = in / size, c = kTextureChannels;
  const size_t texels = static_cast<size_t>(size) * size;
  out->assign(c * texels, 0.f);
  out_valid->assign(texels, 0.f);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      double sum[kTextureChannels] = {};
      int n = 0;
      for (int dy = 0; dy < k; ++dy) {
        for (int dx = 0; dx < k; ++dx) {
          const size_t t = static_cast<size_t>(y * k + dy) * in + x * k + dx;
          if (!valid[t]) continue;
          for (int ch = 0; ch < c; ++ch) sum[ch] += maps[c * t + ch];
          ++n;
        }
      }
      if (n == 0) continue;
      const size_t t = static_cast<size_t>(y) * size + x;
      for (int ch = 0; ch < c; ++ch) (*out)[ch * texels + t] = static_cast<float>(sum[ch] / n);
      (*out_valid)[t] = 1;
    }
  }
}

absl::StatusOr<NeutralTextures> LoadNeutralTextures(const AssetDataset& d, int net_size) {
  NeutralTextures n;
  const std::string& dir = d.neutral_textures_dir;
  const int size = d.neutral_texture_size;
  Image* images[] = {&n.albedo, &n.specular, &n.normal};
  const char* names[] = {"albedo.exr", "specular.exr", "normal_tangent.exr"};
  const int channels[] = {4, 1, 3};
  for (int i = 0; i < 3; ++i) {
    const std::string path = dir + "/" + names[i];
    STAGE_ASSIGN_OR_RETURN(*images[i], ReadImageFile(path));
    if (images[i]->width != size || images[i]->height != size || images[i]->channels != channels[i]) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": ", images[i]->width, " x ", images[i]->height, " x ",
                                                     images[i]->channels, ", not the ", size, " x ", size, " x ",
                                                     channels[i], " the dataset ", d.path, " says"));
    }
  }
  if (d.texture_size % net_size != 0) {
    return absl::InvalidArgumentError(absl::StrCat(d.path, ": its textures (", d.texture_size,
                                                   " texels across) do not divide into the net's ", net_size));
  }
  std::vector<float> maps;
  std::vector<uint8_t> valid;
  STAGE_RETURN_IF_ERROR(ReadDatasetFrameTextures(d, 0, &maps, &valid));
  n.net_size = net_size;
  DownsampleTextureMap(maps.data(), valid.data(), d.texture_size, net_size, &n.net, &n.net_valid);
  return n;
}

TextureImages NetTextureImages(const std::vector<float>& decoded, int size) {
  const size_t texels = static_cast<size_t>(size) * size;
  TextureImages out{Image(size, size, 3), Image(size, size, 1), Image(size, size, 3)};
  for (size_t t = 0; t < texels; ++t) {
    for (int c = 0; c < 3; ++c) out.albedo.pixels[3 * t + c] = std::max(0.f, decoded[c * texels + t]);
    out.specular.pixels[t] = std::max(0.f, decoded[3 * texels + t]);
    Eigen::Vector3f n(decoded[4 * texels + t], decoded[5 * texels + t], decoded[6 * texels + t]);
    n = n.norm() > 0 ? n.normalized() : Eigen::Vector3f::UnitZ();
    std::copy(n.data(), n.data() + 3, &out.normal.pixels[3 * t]);
  }
  return out;
}

TextureImages ApplyWrinkleMaps(const NeutralTextures& neutral, const std::vector<float>& decoded) {
  const int s = neutral.net_size, size = neutral.albedo.width, c = kTextureChannels;
  const size_t net_texels = static_cast<size_t>(s) * s;
  // The wrinkle maps at the net's size, texel-interleaved.
  std::vector<float> wrinkle(c * net_texels, 0.f);
  for (size_t t = 0; t < net_texels; ++t) {
    if (!neutral.net_valid[t]) continue;
    for (int ch = 0; ch < c; ++ch)
      wrinkle[c * t + ch] = decoded[ch * net_texels + t] - neutral.net[ch * net_texels + t];
  }
  TextureImages out{Image(size, size, 3), Image(size, size, 1), Image(size, size, 3)};
  const double ratio = static_cast<double>(s) / size;
  for (int y = 0; y < size; ++y) {
    // Texel centres: (i + 0.5) at the full size is (i + 0.5) * ratio at the net's; bilinear, clamped at the edge.
    const double sy = std::clamp((y + 0.5) * ratio - 0.5, 0.0, s - 1.0);
    const int y0 = static_cast<int>(sy), y1 = std::min(y0 + 1, s - 1);
    const float fy = static_cast<float>(sy - y0);
    for (int x = 0; x < size; ++x) {
      const size_t t = static_cast<size_t>(y) * size + x;
      if (neutral.albedo.pixels[4 * t + 3] < 0.5f) continue;
      const double sx = std::clamp((x + 0.5) * ratio - 0.5, 0.0, s - 1.0);
      const int x0 = static_cast<int>(sx), x1 = std::min(x0 + 1, s - 1);
      const float fx = static_cast<float>(sx - x0);
      float w[kTextureChannels];
      for (int ch = 0; ch < c; ++ch) {
        auto at = [&](int yy, int xx) { return wrinkle[c * (static_cast<size_t>(yy) * s + xx) + ch]; };
        w[ch] = (1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x1)) + fy * ((1 - fx) * at(y1, x0) + fx * at(y1, x1));
      }
      for (int ch = 0; ch < 3; ++ch)
        out.albedo.pixels[3 * t + ch] = std::max(0.f, neutral.albedo.pixels[4 * t + ch] + w[ch]);
      out.specular.pixels[t] = std::max(0.f, neutral.specular.pixels[t] + w[3]);
      const Eigen::Vector3f n =
          Eigen::Map<const Eigen::Vector3f>(&neutral.normal.pixels[3 * t]) + Eigen::Vector3f(w[4], w[5], w[6]);
      const Eigen::Vector3f unit = n.norm() > 0 ? n.normalized() : Eigen::Vector3f::UnitZ();
      std::copy(unit.data(), unit.data() + 3, &out.normal.pixels[3 * t]);
    }
  }
  return out;
}

}  // namespace asset_internal

namespace {

using asset_internal::LoadTextureNet;

nlohmann::json SplitJson(const TextureSplitError& x) {
  return {{"frames", x.frames},
          {"albedo_levels", x.albedo_levels},
          {"normal_deg", x.normal_deg},
          {"specular_relative", x.specular_relative}};
}

// The nets and latents the texture mapping trains and is evaluated on.
struct TextureAsset {
  PreparedData geometry_data;  // at the geometry net's size
  PreparedTextures textures;   // at the texture net's size
  std::unique_ptr<GeometryVae> geometry;
  std::unique_ptr<TextureVae> texture;
  std::unique_ptr<LatentMapping> mapping;
  std::vector<std::vector<float>> geometry_latents, texture_latents;  // per frame, the means
};

absl::StatusOr<TextureAsset> LoadTextureAsset(const std::string& dataset, const std::string& geometry_run,
                                              const std::string& texture_run, int threads) {
  TextureAsset a;
  STAGE_ASSIGN_OR_RETURN(a.geometry, asset_internal::LoadGeometryRun(geometry_run, dataset, &a.geometry_data, threads));
  STAGE_ASSIGN_OR_RETURN(a.texture, LoadTextureNet(texture_run, threads));
  STAGE_ASSIGN_OR_RETURN(a.textures, PrepareTextures(dataset, a.texture->options().input_size));
  const int g = a.geometry->options().geometry_latent;
  for (int64_t f = 0; f < a.textures.dataset.frames(); ++f) {
    const NetMaps& m = a.geometry_data.maps;
    STAGE_ASSIGN_OR_RETURN(std::vector<float> z, a.geometry->Encode(m.maps[f], m.valid[f], 1));
    z.resize(static_cast<size_t>(g));
    a.geometry_latents.push_back(std::move(z));
    STAGE_ASSIGN_OR_RETURN(std::vector<float> t,
                           a.texture->Encode(a.textures.maps.maps[f], a.textures.maps.valid[f], 1));
    a.texture_latents.push_back(std::move(t));
  }
  return a;
}

// The evaluation of `a.mapping` (see TextureDrivenEvaluation); driven where the dataset's directory holds a mapping
// run (and through its fine-tuned path where one is finished).
absl::StatusOr<TextureDrivenEvaluation> EvaluateTextureMapping(const TextureAsset& a, const std::string& dataset,
                                                               const std::string& geometry_run) {
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  const NetMaps& m = a.textures.maps;
  const AssetDataset& d = a.textures.dataset;
  const std::vector<uint8_t> skin = SkinMask(face, m.size);
  absl::Status failed;
  auto textures_of = [&](const std::vector<float>& geometry_latent) {
    absl::StatusOr<std::vector<float>> out = a.mapping->Map(geometry_latent, 1);
    if (out.ok()) out = a.texture->Decode(*out, 1);
    if (!out.ok()) failed = out.status();
    return out.ok() ? *out : m.maps[0];
  };
  TextureDrivenEvaluation e;
  for (int s = 0; s < 3; ++s) {
    const std::vector<int64_t> frames = asset_internal::FramesOf(d, static_cast<SampleSplit>(s));
    e.from_geometry[s] = TextureError(m, skin, frames, [&](int64_t f) { return textures_of(a.geometry_latents[f]); });
    e.autoencoded[s] = TextureError(m, skin, frames, [&](int64_t f) {
      absl::StatusOr<std::vector<float>> out = a.texture->Decode(a.texture_latents[f], 1);
      if (!out.ok()) failed = out.status();
      return out.ok() ? *out : m.maps[0];
    });
    e.neutral[s] = TextureError(m, skin, frames, [&](int64_t) { return m.maps[0]; });
  }
  const std::string mapping_run = asset_internal::RunDir("", dataset, "mapping");
  if (!d.cameras.empty() && fs::exists(mapping_run + "/mapping.pt")) {
    const std::string finetune = asset_internal::FineTuneRun("", dataset);
    STAGE_ASSIGN_OR_RETURN(const asset_internal::DrivenAsset driven,
                           asset_internal::LoadDriven(dataset, geometry_run, "", "", finetune, 0));
    e.driven_through = finetune.empty() ? "mapping" : "finetune";
    for (int c = 0; c < driven.crops.cameras; ++c) {
      TextureDrivenEvaluation::Camera camera;
      camera.id = d.cameras[c];
      camera.trained = std::find(driven.trained.begin(), driven.trained.end(), c) != driven.trained.end();
      for (int s = 0; s < 3; ++s) {
        std::vector<int64_t> frames;
        for (int64_t f : asset_internal::FramesOf(d, static_cast<SampleSplit>(s))) {
          if (asset_internal::ImageValid(d, f, c)) frames.push_back(f);
        }
        camera.error[s] = TextureError(m, skin, frames, [&](int64_t f) { return textures_of(driven.DrivenOf(f, c)); });
      }
      e.cameras.push_back(camera);
    }
  }
  if (!failed.ok()) return failed;
  return e;
}

}  // namespace

absl::Status TextureMappingJob::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("texture mapping: no dataset");
  if (mapping.input != 0 || mapping.output != 0) {
    return absl::InvalidArgumentError("texture mapping: its sizes are the VAEs' latents' (leave them 0)");
  }
  if (!(input_noise >= 0 && input_noise <= 2)) {
    return absl::InvalidArgumentError(absl::StrCat("texture mapping: input noise ", input_noise, " is not in 0..2"));
  }
  return schedule.Validate();
}

absl::StatusOr<TextureMappingResult> TrainTextureMapping(const TextureMappingJob& job) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  const std::string geometry_run = asset_internal::RunDir(job.geometry_run, job.dataset, "geometry");
  const std::string texture_run = asset_internal::RunDir(job.texture_run, job.dataset, "texture");
  STAGE_ASSIGN_OR_RETURN(TextureAsset a, LoadTextureAsset(job.dataset, geometry_run, texture_run, job.mapping.threads));
  const std::vector<int64_t>& train = a.textures.train;
  LatentMappingOptions o = job.mapping;
  o.input = a.geometry->options().geometry_latent;
  o.output = a.texture->options().texture_latent;
  std::vector<std::vector<float>> inputs, targets;
  for (int64_t f : train) {
    inputs.push_back(a.geometry_latents[f]);
    targets.push_back(a.texture_latents[f]);
  }
  std::vector<float> input_mean, input_spread, target_mean, target_spread;
  asset_internal::MeanAndSpread(inputs, o.input, &input_mean, &input_spread);
  asset_internal::MeanAndSpread(targets, o.output, &target_mean, &target_spread);
  STAGE_ASSIGN_OR_RETURN(a.mapping, LatentMapping::Create(o, target_mean, target_spread));

  TextureMappingResult result;
  result.output_dir = asset_internal::RunDir(job.output_dir, job.dataset, "texture_mapping");
  result.parameters = a.mapping->parameter_count();
  LatentMapping& net = *a.mapping;
  internal::TrainingLoop loop;
  loop.dir = result.output_dir;
  loop.what = "texture mapping";
  loop.options = {{"network", "texture_mapping"},
                  {"input", o.input},
                  {"output", o.output},
                  {"hidden", o.hidden},
                  {"layers", o.layers},
                  {"seed", o.seed},
                  {"input_noise", job.input_noise},
                  {"dataset", fs::absolute(job.dataset).lexically_normal().string()},
                  {"dataset_id", asset_internal::DatasetId(a.textures.dataset)},
                  {"threads", TorchThreadCount(o.threads)}};
  STAGE_RETURN_IF_ERROR(
      asset_internal::AddRunIdentities({{"geometry", geometry_run}, {"texture", texture_run}}, &loop.options));
  asset_internal::AddScheduleJson(job.schedule, &loop.options);
  loop.loss_names = {"total"};
  loop.schedule = job.schedule;
  loop.seed = o.seed;
  loop.save = [&net](const std::string& path) { return net.Save(path); };
  loop.load = [&net](const std::string& path) { return net.Load(path); };
  loop.step = [&](std::mt19937_64& rng, double rate) -> absl::StatusOr<std::vector<double>> {
    const int b = job.schedule.batch;
    std::vector<float> x, y, noise;
    for (int n = 0; n < b; ++n) {
      const size_t i = rng() % train.size();
      x.insert(x.end(), inputs[i].begin(), inputs[i].end());
      y.insert(y.end(), targets[i].begin(), targets[i].end());
      for (int k = 0; k < o.input; ++k) {
        noise.push_back(static_cast<float>(job.input_noise) * input_spread[k] * internal::Normal(rng));
      }
    }
    STAGE_ASSIGN_OR_RETURN(const double loss, net.TrainStep(x, y, noise, b, rate));
    return std::vector<double>{loss};
  };
  if (job.progress) {
    loop.progress = [&](int64_t step, int64_t total, const std::vector<double>& l) {
      return job.progress(step, total, l[0]);
    };
  }
  STAGE_ASSIGN_OR_RETURN(const internal::TrainingOutcome outcome, internal::RunTraining(loop));
  result.resumed_from = outcome.resumed_from;
  for (const auto& l : outcome.losses) result.losses.push_back(l[0]);
  result.steps = job.schedule.iterations;
  STAGE_RETURN_IF_ERROR(net.Save(result.output_dir + "/texture_mapping.pt"));
  STAGE_ASSIGN_OR_RETURN(result.evaluation, EvaluateTextureMapping(a, job.dataset, geometry_run));
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/evaluation.json",
                                            TextureDrivenEvaluationJson(result.evaluation) + "\n"));
  return result;
}

absl::StatusOr<TextureDrivenEvaluation> EvaluateDrivenTextures(const std::string& dataset,
                                                               const std::string& geometry_run,
                                                               const std::string& texture_run,
                                                               const std::string& texture_mapping_run) {
  const std::string run = asset_internal::RunDir(texture_mapping_run, dataset, "texture_mapping");
  const std::string geometry = asset_internal::RunTrainedFrom(geometry_run, run, "geometry", dataset);
  const std::string texture = asset_internal::RunTrainedFrom(texture_run, run, "texture", dataset);
  STAGE_ASSIGN_OR_RETURN(TextureAsset a, LoadTextureAsset(dataset, geometry, texture, 0));
  STAGE_ASSIGN_OR_RETURN(
      a.mapping, asset_internal::LoadTextureMappingNet(run, geometry, texture, a.geometry->options().geometry_latent,
                                                       a.texture->options().texture_latent, 0));
  return EvaluateTextureMapping(a, dataset, geometry);
}

std::string TextureDrivenEvaluationJson(const TextureDrivenEvaluation& e) {
  nlohmann::json j;
  const char* names[3] = {"train", "held_out_block", "held_out_sequence"};
  for (int s = 0; s < 3; ++s) {
    j[names[s]]["from_geometry"] = SplitJson(e.from_geometry[s]);
    j[names[s]]["autoencoded"] = SplitJson(e.autoencoded[s]);
    j[names[s]]["neutral"] = SplitJson(e.neutral[s]);
    for (const auto& c : e.cameras) {
      j[names[s]]["cameras"][c.id] = SplitJson(c.error[s]);
      j[names[s]]["cameras"][c.id]["trained"] = c.trained;
    }
  }
  j["driven_through"] = e.driven_through;
  return j.dump();
}

std::string FormatTextureDrivenEvaluation(const TextureDrivenEvaluation& e) {
  std::string out = absl::StrFormat("%-18s %6s  %-30s %14s %12s %12s\n", "split", "frames", "textures", "albedo levels",
                                    "normal deg", "specular %");
  const char* names[3] = {"train", "held-out blocks", "held-out sequence"};
  auto row = [&](int s, const std::string& what, const TextureSplitError& x) {
    absl::StrAppendFormat(&out, "%-18s %6d  %-30s %14.3f %12.3f %12.2f\n", names[s], x.frames, what, x.albedo_levels,
                          x.normal_deg, 100 * x.specular_relative);
  };
  for (int s = 0; s < 3; ++s) {
    for (const auto& c : e.cameras) {
      row(s, absl::StrCat("driven from ", c.id, c.trained ? "" : " (held out)"), c.error[s]);
    }
    row(s, "from the frame's geometry", e.from_geometry[s]);
    row(s, "texture VAE (ceiling)", e.autoencoded[s]);
    row(s, "neutral frame", e.neutral[s]);
  }
  absl::StrAppend(&out, e.driven_through.empty()
                            ? "(not driven from images: the dataset's directory has no mapping run)\n"
                            : absl::StrCat("(driven through the ", e.driven_through,
                                           "; the goal from a held-out view: 3 albedo levels on the skin)\n"));
  return out;
}

absl::Status TextureTrainJob::Validate() const {
  if (dataset.empty()) return absl::InvalidArgumentError("texture training: no dataset");
  STAGE_RETURN_IF_ERROR(texture.Validate());
  if (texture.channels != kTextureChannels) {
    return absl::InvalidArgumentError(absl::StrCat("texture training: the dataset's textures have ", kTextureChannels,
                                                   " channels, not ", texture.channels));
  }
  return schedule.Validate();
}

absl::StatusOr<TextureTrainResult> TrainTextureAsset(const TextureTrainJob& job) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  STAGE_ASSIGN_OR_RETURN(const PreparedTextures data, PrepareTextures(job.dataset, job.texture.input_size));
  TextureTrainResult result;
  result.output_dir = asset_internal::RunDir(job.output_dir, job.dataset, "texture");
  STAGE_ASSIGN_OR_RETURN(
      auto net, job.direct
                    ? TextureVae::Create(job.texture, std::vector<float>(data.mean.size(), 0.f), DirectScale(data))
                    : TextureVae::Create(job.texture, data.mean, data.scale));
  result.parameters = net->parameter_count();
  internal::TrainingLoop loop;
  loop.dir = result.output_dir;
  loop.what = "texture VAE";
  loop.options = OptionsJson(job, asset_internal::DatasetId(data.dataset));
  loop.loss_names = {"total", "reconstruction", "kl"};
  loop.schedule = job.schedule;
  loop.seed = job.texture.seed;
  loop.save = [&net](const std::string& path) { return net->Save(path); };
  loop.load = [&net](const std::string& path) { return net->Load(path); };
  loop.step = [&](std::mt19937_64& rng, double rate) -> absl::StatusOr<std::vector<double>> {
    STAGE_ASSIGN_OR_RETURN(const TextureLosses l, net->TrainStep(DrawBatch(data, job, rng), rate));
    return std::vector<double>{l.total, l.reconstruction, l.kl};
  };
  auto losses_of = [](const std::vector<double>& v) { return TextureLosses{v[0], v[1], v[2]}; };
  if (job.progress) {
    loop.progress = [&](int64_t step, int64_t total, const std::vector<double>& l) {
      return job.progress(step, total, losses_of(l));
    };
  }
  STAGE_ASSIGN_OR_RETURN(const internal::TrainingOutcome outcome, internal::RunTraining(loop));
  result.resumed_from = outcome.resumed_from;
  for (const auto& l : outcome.losses) result.losses.push_back(losses_of(l));
  result.steps = job.schedule.iterations;
  STAGE_RETURN_IF_ERROR(net->Save(result.output_dir + "/texture_vae.pt"));
  STAGE_RETURN_IF_ERROR(net->ExportTorchScript(result.output_dir + "/texture_vae.torchscript.pt"));
  STAGE_ASSIGN_OR_RETURN(result.evaluation, Evaluate(*net, data));
  STAGE_RETURN_IF_ERROR(
      WriteFileAtomically(result.output_dir + "/evaluation.json", TextureEvaluationJson(result.evaluation) + "\n"));
  return result;
}

absl::StatusOr<TextureEvaluation> EvaluateTextureAsset(const std::string& dataset, const std::string& run_dir) {
  STAGE_ASSIGN_OR_RETURN(auto net, LoadTextureNet(run_dir, 0));
  STAGE_ASSIGN_OR_RETURN(const PreparedTextures data, PrepareTextures(dataset, net->options().input_size));
  return Evaluate(*net, data);
}

std::string TextureEvaluationJson(const TextureEvaluation& e) {
  nlohmann::json j;
  const char* names[3] = {"train", "held_out_block", "held_out_sequence"};
  for (int s = 0; s < 3; ++s) {
    for (auto [model, errors] : {std::pair{"vae", e.vae}, std::pair{"pca", e.pca}, std::pair{"neutral", e.neutral}}) {
      j[names[s]][model] = SplitJson(errors[s]);
    }
  }
  return j.dump();
}

std::string FormatTextureEvaluation(const TextureEvaluation& e) {
  std::string out = absl::StrFormat("%-18s %6s  %-8s %14s %12s %12s\n", "split", "frames", "model", "albedo levels",
                                    "normal deg", "specular %");
  const char* names[3] = {"train", "held-out blocks", "held-out sequence"};
  for (int s = 0; s < 3; ++s) {
    for (auto [model, errors] : {std::pair{"VAE", e.vae}, std::pair{"PCA", e.pca}, std::pair{"neutral", e.neutral}}) {
      const TextureSplitError& x = errors[s];
      absl::StrAppendFormat(&out, "%-18s %6d  %-8s %14.3f %12.3f %12.2f\n", names[s], x.frames, model, x.albedo_levels,
                            x.normal_deg, 100 * x.specular_relative);
    }
  }
  absl::StrAppend(&out,
                  "(albedo: RMSE in 0..255 levels of its sRGB encoding on the skin; the goal driven from a held-out "
                  "view is 3 levels; these are the textures encoded and decoded)\n");
  return out;
}

}  // namespace stage::processing
