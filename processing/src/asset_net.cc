// The neural asset's networks (docs/asset.md), as the torch module implements them (torch_nets.h): see
// asset_net.h. With warp_net.cc, the only sources that include torch's headers.
#include <torch/script.h>
#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <filesystem>

#include "absl/strings/str_cat.h"
#include "stage/common/status.h"
#include "torch_nets.h"
#include "torch_support.h"

namespace stage::processing {
namespace {

namespace nnf = torch::nn::functional;
using internal::ConvShape;
using internal::ShapeOf;
constexpr const char* kNet = "geometry VAE";

torch::Tensor Leaky(const torch::Tensor& x) {
  return nnf::leaky_relu(x, nnf::LeakyReLUFuncOptions().negative_slope(0.1));
}

// An image of `in` channels -> `outputs` numbers (the latents' means and log-variances): a 3 x 3 convolution, then
// stride-2 3 x 3 convolutions down the levels, and a linear layer.
struct EncoderImpl : torch::nn::Module {
  EncoderImpl(const ConvShape& shape, int in, int outputs) {
    stem = register_module("stem", torch::nn::Conv2d(torch::nn::Conv2dOptions(in, shape.Channels(0), 3).padding(1)));
    for (int i = 0; i < shape.levels; ++i) {
      downs.push_back(register_module(
          "down" + std::to_string(i),
          torch::nn::Conv2d(
              torch::nn::Conv2dOptions(shape.Channels(i), shape.Channels(i + 1), 3).stride(2).padding(1))));
    }
    head =
        register_module("head", torch::nn::Linear(shape.Channels(shape.levels) * shape.side() * shape.side(), outputs));
  }
  torch::Tensor forward(torch::Tensor x) {
    x = Leaky(stem(x));
    for (auto& d : downs) x = Leaky(d(x));
    return head(x.flatten(1));
  }
  torch::nn::Conv2d stem{nullptr};
  std::vector<torch::nn::Conv2d> downs;
  torch::nn::Linear head{nullptr};
};
TORCH_MODULE(Encoder);

// `latent` numbers -> an image of `out` channels: a linear layer to the coarsest level, then bilinear 2x upsamplings
// each with a 3 x 3 convolution, and a last 3 x 3 convolution.
struct DecoderImpl : torch::nn::Module {
  DecoderImpl(const ConvShape& shape, int latent, int out_channels)
      : side(shape.side()), top_channels(shape.Channels(shape.levels)) {
    in = register_module("input", torch::nn::Linear(latent, top_channels * side * side));
    for (int i = shape.levels - 1; i >= 0; --i) {
      ups.push_back(register_module(
          "up" + std::to_string(i),
          torch::nn::Conv2d(torch::nn::Conv2dOptions(shape.Channels(i + 1), shape.Channels(i), 3).padding(1))));
    }
    out = register_module("out",
                          torch::nn::Conv2d(torch::nn::Conv2dOptions(shape.Channels(0), out_channels, 3).padding(1)));
  }
  torch::Tensor forward(const torch::Tensor& z) {
    torch::Tensor x = Leaky(in(z)).view({z.size(0), top_channels, side, side});
    for (auto& u : ups) {
      x = nnf::interpolate(x, nnf::InterpolateFuncOptions()
                                  .scale_factor(std::vector<double>{2, 2})
                                  .mode(torch::kBilinear)
                                  .align_corners(false));
      x = Leaky(u(x));
    }
    return out(x);
  }
  int side, top_channels;
  torch::nn::Linear in{nullptr};
  std::vector<torch::nn::Conv2d> ups;
  torch::nn::Conv2d out{nullptr};
};
TORCH_MODULE(Decoder);

// Pose latent -> a rotation (6D: two columns, orthonormalized) and a translation (normalized units).
struct PoseMlpImpl : torch::nn::Module {
  explicit PoseMlpImpl(const GeometryVaeOptions& o) {
    hidden = register_module("hidden", torch::nn::Linear(o.pose_latent, 64));
    out = register_module("out", torch::nn::Linear(64, 9));
    // Starts at the identity and no translation.
    torch::NoGradGuard no_grad;
    out->weight.mul_(0.01);
    out->bias.copy_(torch::tensor({1.f, 0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 0.f}));
  }
  // (B x 3 x 3 rotations, B x 3 translations).
  std::pair<torch::Tensor, torch::Tensor> forward(const torch::Tensor& z) {
    const torch::Tensor y = out(Leaky(hidden(z)));
    const torch::Tensor a = y.slice(1, 0, 3), b = y.slice(1, 3, 6);
    const torch::Tensor c1 = nnf::normalize(a, nnf::NormalizeFuncOptions().dim(1));
    const torch::Tensor c2 = nnf::normalize(b - (c1 * b).sum(1, true) * c1, nnf::NormalizeFuncOptions().dim(1));
    const torch::Tensor c3 = torch::cross(c1, c2, 1);
    return {torch::stack({c1, c2, c3}, 2), y.slice(1, 6, 9)};
  }
  torch::nn::Linear hidden{nullptr}, out{nullptr};
};
TORCH_MODULE(PoseMlp);

struct VaeImpl : torch::nn::Module {
  VaeImpl(const GeometryVaeOptions& o, const torch::Tensor& mean_mm, float scale_mm)
      : geometry_latent(o.geometry_latent), pose_latent(o.pose_latent) {
    encoder = register_module("encoder", Encoder(ShapeOf(o), 4, 2 * (o.geometry_latent + o.pose_latent)));
    decoder = register_module("decoder", Decoder(ShapeOf(o), o.geometry_latent, 3));
    pose = register_module("pose", PoseMlp(o));
    mean = register_buffer("mean", mean_mm);
    scale = register_buffer("scale", torch::tensor({scale_mm}));
  }
  torch::Tensor Normalize(const torch::Tensor& mm, const torch::Tensor& valid) {
    return torch::cat({(mm - mean) / scale * valid, valid}, 1);
  }
  // The rigid motion (least squares over valid texels, Kabsch) that takes each map onto the mean map: the encoder
  // sees maps so aligned, and the pose is that motion undone after a residual the pose latent predicts.
  struct Alignment {
    torch::Tensor rotation;     // B x 3 x 3: aligned = R (map - map_centre) + mean_centre
    torch::Tensor map_centre;   // B x 3
    torch::Tensor mean_centre;  // B x 3
  };
  Alignment Align(const torch::Tensor& mm, const torch::Tensor& valid) {
    torch::NoGradGuard no_grad;
    const int64_t b = mm.size(0);
    const torch::Tensor n = valid.sum({2, 3}).clamp_min(1);  // B x 1
    Alignment a;
    a.map_centre = (mm * valid).sum({2, 3}) / n;
    a.mean_centre = (mean * valid).sum({2, 3}) / n;
    const torch::Tensor p = ((mm - a.map_centre.view({b, 3, 1, 1})) * valid).view({b, 3, -1});
    const torch::Tensor m = ((mean - a.mean_centre.view({b, 3, 1, 1})) * valid).view({b, 3, -1});
    const auto [u, singular, vh] = torch::linalg::svd(m.bmm(p.transpose(1, 2)), /*full_matrices=*/false, c10::nullopt);
    const torch::Tensor d = torch::sign(torch::linalg::det(u.bmm(vh)));
    const torch::Tensor flip = torch::stack({torch::ones_like(d), torch::ones_like(d), d}, 1);  // B x 3
    a.rotation = (u * flip.unsqueeze(1)).bmm(vh);
    return a;
  }
  static torch::Tensor Apply(const torch::Tensor& r, const torch::Tensor& maps) {
    return torch::einsum("bij,bjhw->bihw", {r, maps});
  }
  torch::Tensor Aligned(const torch::Tensor& mm, const Alignment& a) {
    const int64_t b = mm.size(0);
    return Apply(a.rotation, mm - a.map_centre.view({b, 3, 1, 1})) + a.mean_centre.view({b, 3, 1, 1});
  }
  // The decoded map (mm, the head's frame) moved by the pose latent's residual motion, then by the alignment undone.
  torch::Tensor Posed(const torch::Tensor& decoded_mm, const torch::Tensor& z_pose, const Alignment& a) {
    const int64_t b = decoded_mm.size(0);
    const auto [r, t] = pose->forward(z_pose);
    const torch::Tensor moved =
        Apply(r, decoded_mm - a.mean_centre.view({b, 3, 1, 1})) + (scale * t).view({b, 3, 1, 1});
    return Apply(a.rotation.transpose(1, 2), moved) + a.map_centre.view({b, 3, 1, 1});
  }
  int geometry_latent, pose_latent;
  Encoder encoder{nullptr};
  Decoder decoder{nullptr};
  PoseMlp pose{nullptr};
  torch::Tensor mean, scale;
};
TORCH_MODULE(Vae);

torch::Tensor FromVector(const std::vector<float>& v, std::vector<int64_t> shape) {
  return torch::from_blob(const_cast<float*>(v.data()), shape, torch::kFloat32).clone();
}

std::vector<float> ToVector(const torch::Tensor& t) {
  const torch::Tensor c = t.contiguous();
  return std::vector<float>(c.data_ptr<float>(), c.data_ptr<float>() + c.numel());
}

absl::Status CheckSize(const std::vector<float>& v, int64_t expected, const char* what, const char* net = kNet) {
  if (static_cast<int64_t>(v.size()) == expected) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(net, ": ", what, " holds ", v.size(), " values, not ", expected));
}

// Adam's rate for the next step.
void SetLearningRate(torch::optim::Adam& adam, double learning_rate) {
  for (auto& group : adam.param_groups()) static_cast<torch::optim::AdamOptions&>(group.options()).lr(learning_rate);
}

// The KL divergence of N(mu, exp(logvar)) from N(0, I), summed over the latent's dimensions, mean over the batch.
torch::Tensor Kl(const torch::Tensor& mu, const torch::Tensor& logvar) {
  return (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp())).sum(1).mean();
}

int64_t CountParameters(const torch::nn::Module& net) {
  int64_t n = 0;
  for (const auto& p : net.parameters()) n += p.numel();
  return n;
}

// A net's weights and its optimizer's state in one torch archive, written atomically.
absl::Status SaveArchive(const torch::nn::Module& net, torch::optim::Adam& adam, const std::string& path,
                         const char* what) {
  try {
    torch::serialize::OutputArchive archive;
    net.save(archive);
    torch::serialize::OutputArchive state;
    adam.save(state);
    archive.write("adam", state);
    const std::string tmp = path + ".tmp";
    archive.save_to(tmp);
    std::error_code ec;
    std::filesystem::rename(tmp, path, ec);
    if (ec) return absl::UnavailableError(absl::StrCat(path, ": ", ec.message()));
    return absl::OkStatus();
  } catch (const std::exception& e) {
    return internal::TorchError(what, absl::StrCat("saving ", path), e);
  }
}

absl::Status LoadArchive(torch::nn::Module& net, torch::optim::Adam& adam, const std::string& path, const char* what) {
  if (!std::filesystem::exists(path)) return absl::NotFoundError(absl::StrCat(path, ": no such checkpoint"));
  try {
    torch::serialize::InputArchive archive;
    archive.load_from(path);
    // Torch's load takes the file's shapes without a word: a net of other options would fail later, or decode
    // nonsense. Compare them here.
    auto shapes = [&net] {
      std::vector<std::pair<std::string, std::vector<int64_t>>> out;
      for (const auto& p : net.named_parameters()) out.emplace_back(p.key(), p.value().sizes().vec());
      for (const auto& b : net.named_buffers()) out.emplace_back(b.key(), b.value().sizes().vec());
      return out;
    };
    const auto before = shapes();
    net.load(archive);
    const auto after = shapes();
    for (size_t i = 0; i < before.size(); ++i) {
      if (after[i].second != before[i].second) {
        return absl::FailedPreconditionError(absl::StrCat(path, ": not a checkpoint of this ", what, " (",
                                                          before[i].first,
                                                          " has another shape: a net of other options)"));
      }
    }
    torch::serialize::InputArchive state;
    archive.read("adam", state);
    adam.load(state);
    return absl::OkStatus();
  } catch (const std::exception& e) {
    const std::string message = e.what();
    return absl::FailedPreconditionError(
        absl::StrCat(path, ": not a checkpoint of this ", what, " (", message.substr(0, message.find('\n')), ")"));
  }
}

// Weighted mean of the squared difference over the texels (3 channels each); `weight` 0 where not valid.
torch::Tensor MaskedMse(const torch::Tensor& a, const torch::Tensor& b, const torch::Tensor& weight) {
  return ((a - b).pow(2) * weight).sum() / (3 * weight.sum()).clamp_min(1);
}

}  // namespace

struct GeometryVaeState {
  GeometryVaeOptions options;
  Vae net{nullptr};
  std::unique_ptr<torch::optim::Adam> adam;

  int64_t latents() const { return options.geometry_latent + options.pose_latent; }
  absl::Status CheckMaps(const std::vector<float>& maps, const std::vector<float>& valid, int64_t batch) const {
    const int64_t texels = static_cast<int64_t>(options.input_size) * options.input_size;
    if (auto st = CheckSize(maps, 3 * batch * texels, "the maps"); !st.ok()) return st;
    return CheckSize(valid, batch * texels, "the validity");
  }
  // The latents' means of `batch` maps (mm) and validity, in evaluation mode, and the alignment they were encoded
  // under.
  torch::Tensor Means(const std::vector<float>& maps, const std::vector<float>& valid, int64_t batch,
                      VaeImpl::Alignment* alignment) {
    const int64_t s = options.input_size;
    net->eval();
    const torch::Tensor mm = FromVector(maps, {batch, 3, s, s}), v = FromVector(valid, {batch, 1, s, s});
    *alignment = net->Align(mm, v);
    return net->encoder->forward(net->Normalize(net->Aligned(mm, *alignment), v)).slice(1, 0, latents());
  }
};

class TorchGeometryVae final : public internal::GeometryVaeNet {
 public:
  explicit TorchGeometryVae(std::unique_ptr<GeometryVaeState> impl) : impl_(std::move(impl)) {}
  absl::StatusOr<GeometryLosses> TrainStep(const GeometryBatch& batch, double learning_rate) override;
  absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& maps, const std::vector<float>& valid,
                                            int batch) const override;
  absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& geometry_latents, int batch) const override;
  absl::StatusOr<std::vector<float>> Reposed(const std::vector<float>& maps, const std::vector<float>& valid,
                                             int batch) const override;
  absl::Status Save(const std::string& path) const override;
  absl::Status Load(const std::string& path) override;
  absl::Status ExportTorchScript(const std::string& path) const override;
  const GeometryVaeOptions& options() const override;
  int64_t parameter_count() const override;
  std::unique_ptr<GeometryVaeState> impl_;
};

absl::StatusOr<std::unique_ptr<internal::GeometryVaeNet>> internal::MakeGeometryVae(const GeometryVaeOptions& options,
                                                                                    const std::vector<float>& mean,
                                                                                    float scale) {
  const int64_t s2 = static_cast<int64_t>(options.input_size) * options.input_size;
  if (auto s = CheckSize(mean, 3 * s2, "the mean map"); !s.ok()) return s;
  if (!(scale > 0)) return absl::InvalidArgumentError(absl::StrCat(kNet, ": scale ", scale, " is not positive"));
  try {
    internal::SetThreads(options.threads);
    auto impl = std::make_unique<GeometryVaeState>();
    impl->options = options;
    impl->net = internal::Seeded(options.seed, [&] {
      return Vae(options, FromVector(mean, {1, 3, options.input_size, options.input_size}), scale);
    });
    impl->adam = std::make_unique<torch::optim::Adam>(impl->net->parameters(), torch::optim::AdamOptions(1e-3));
    return std::unique_ptr<internal::GeometryVaeNet>(new TorchGeometryVae(std::move(impl)));
  } catch (const std::exception& e) {
    return internal::TorchError(kNet, "creating the net", e);
  }
}

const GeometryVaeOptions& TorchGeometryVae::options() const { return impl_->options; }

int64_t TorchGeometryVae::parameter_count() const { return CountParameters(*impl_->net); }

absl::StatusOr<GeometryLosses> TorchGeometryVae::TrainStep(const GeometryBatch& batch, double learning_rate) {
  const GeometryVaeOptions& o = impl_->options;
  const int64_t b = batch.batch, s = o.input_size, latents = o.geometry_latent + o.pose_latent;
  if (b < 1) return absl::InvalidArgumentError(absl::StrCat(kNet, ": an empty batch"));
  for (auto [v, n, what] :
       {std::tuple{&batch.posed, 3 * b * s * s, "the posed maps"},
        std::tuple{&batch.canonical, 3 * b * s * s, "the canonical maps"},
        std::tuple{&batch.valid, b * s * s, "the validity"}, std::tuple{&batch.noise, b * latents, "the noise"}}) {
    if (auto st = CheckSize(*v, n, what); !st.ok()) return st;
  }
  if (!batch.weight.empty()) {
    if (auto st = CheckSize(batch.weight, b * s * s, "the texels' weights"); !st.ok()) return st;
  }
  try {
    internal::SetThreads(o.threads);
    Vae& net = impl_->net;
    net->train();
    SetLearningRate(*impl_->adam, learning_rate);
    const torch::Tensor posed = FromVector(batch.posed, {b, 3, s, s});
    const torch::Tensor canonical = FromVector(batch.canonical, {b, 3, s, s});
    const torch::Tensor valid = FromVector(batch.valid, {b, 1, s, s});
    const torch::Tensor noise = FromVector(batch.noise, {b, latents});
    const torch::Tensor weight = batch.weight.empty() ? valid : FromVector(batch.weight, {b, 1, s, s}) * valid;
    impl_->adam->zero_grad();
    const VaeImpl::Alignment alignment = net->Align(posed, valid);
    const torch::Tensor stats = net->encoder->forward(net->Normalize(net->Aligned(posed, alignment), valid));
    const torch::Tensor mu = stats.slice(1, 0, latents), logvar = stats.slice(1, latents, 2 * latents).clamp(-10, 10);
    const torch::Tensor z = mu + noise * torch::exp(0.5 * logvar);
    const torch::Tensor decoded = net->decoder->forward(z.slice(1, 0, o.geometry_latent));  // normalized
    const torch::Tensor canonical_n = (canonical - net->mean) / net->scale;
    const torch::Tensor posed_n = (posed - net->mean) / net->scale;
    // The decoded map's gradient stops at the posed loss: it trains the pose (its MLP and the encoder's pose latent),
    // the canonical loss the geometry.
    const torch::Tensor moved_mm =
        net->Posed(net->mean + net->scale * decoded.detach(), z.slice(1, o.geometry_latent, latents), alignment);
    const torch::Tensor moved_n = (moved_mm - net->mean) / net->scale;
    const torch::Tensor canonical_loss = MaskedMse(decoded, canonical_n, weight);
    const torch::Tensor posed_loss = MaskedMse(moved_n, posed_n, weight);
    const torch::Tensor kl = Kl(mu, logvar);
    const torch::Tensor total = canonical_loss + posed_loss + o.kl_weight * kl;
    total.backward();
    impl_->adam->step();
    return GeometryLosses{total.item<double>(), canonical_loss.item<double>(), posed_loss.item<double>(),
                          kl.item<double>()};
  } catch (const std::exception& e) {
    return internal::TorchError(kNet, "training", e);
  }
}

absl::StatusOr<std::vector<float>> TorchGeometryVae::Encode(const std::vector<float>& maps,
                                                            const std::vector<float>& valid, int batch) const {
  if (auto st = impl_->CheckMaps(maps, valid, batch); !st.ok()) return st;
  try {
    internal::SetThreads(impl_->options.threads);
    torch::NoGradGuard no_grad;
    VaeImpl::Alignment alignment;
    return ToVector(impl_->Means(maps, valid, batch, &alignment));
  } catch (const std::exception& e) {
    return internal::TorchError(kNet, "encoding", e);
  }
}

absl::StatusOr<std::vector<float>> TorchGeometryVae::Decode(const std::vector<float>& geometry_latents,
                                                            int batch) const {
  const GeometryVaeOptions& o = impl_->options;
  if (auto st = CheckSize(geometry_latents, int64_t{batch} * o.geometry_latent, "the geometry latents"); !st.ok()) {
    return st;
  }
  try {
    internal::SetThreads(o.threads);
    torch::NoGradGuard no_grad;
    impl_->net->eval();
    const torch::Tensor d = impl_->net->decoder->forward(FromVector(geometry_latents, {batch, o.geometry_latent}));
    return ToVector(impl_->net->mean + impl_->net->scale * d);
  } catch (const std::exception& e) {
    return internal::TorchError(kNet, "decoding", e);
  }
}

absl::StatusOr<std::vector<float>> TorchGeometryVae::Reposed(const std::vector<float>& maps,
                                                             const std::vector<float>& valid, int batch) const {
  const GeometryVaeOptions& o = impl_->options;
  if (auto st = impl_->CheckMaps(maps, valid, batch); !st.ok()) return st;
  try {
    internal::SetThreads(o.threads);
    torch::NoGradGuard no_grad;
    VaeImpl::Alignment alignment;
    const torch::Tensor mu = impl_->Means(maps, valid, batch, &alignment);
    Vae& net = impl_->net;
    const torch::Tensor decoded = net->mean + net->scale * net->decoder->forward(mu.slice(1, 0, o.geometry_latent));
    return ToVector(net->Posed(decoded, mu.slice(1, o.geometry_latent, impl_->latents()), alignment));
  } catch (const std::exception& e) {
    return internal::TorchError(kNet, "reposing", e);
  }
}

absl::Status TorchGeometryVae::Save(const std::string& path) const {
  return SaveArchive(*impl_->net, *impl_->adam, path, kNet);
}

namespace {

// TorchScript's source of the net (the same operations as the modules above, by aten's names: the C++ compiler of
// TorchScript resolves torch.* builtins, not torch.nn.functional). Parameters are attributes named by their path,
// dots as underscores.
// TorchScript of the decoder trunk (DecoderImpl) ending in `x`, from `z`, its parameters under "decoder_".
std::string DecoderScript(const ConvShape& shape) {
  const std::string conv = ", [1, 1], [1, 1], [1, 1], 1)";
  std::string src = "    x = self.leaky(torch.linear(z, self.decoder_input_weight, self.decoder_input_bias))\n";
  src += absl::StrCat("    x = x.view(z.size(0), ", shape.Channels(shape.levels), ", ", shape.side(), ", ",
                      shape.side(), ")\n");
  for (int i = shape.levels - 1; i >= 0; --i) {
    src += "    x = torch.upsample_bilinear2d(x, None, False, [2.0, 2.0])\n";
    src += absl::StrCat("    x = self.leaky(torch.conv2d(x, self.decoder_up", i, "_weight, self.decoder_up", i, "_bias",
                        conv, ")\n");
  }
  return src + absl::StrCat("    x = torch.conv2d(x, self.decoder_out_weight, self.decoder_out_bias", conv, "\n");
}

// TorchScript's leaky(x) and the start of decode(z): the decoder trunk up to its output `x`, for the net to finish.
std::string DecodeScript(const ConvShape& shape) {
  return R"(
def leaky(self, x: Tensor) -> Tensor:
    return torch.leaky_relu(x, 0.1)

def decode(self, z: Tensor) -> Tensor:
)" + DecoderScript(shape);
}

// TorchScript of the encoder trunk (EncoderImpl) from `x` to the first `latents` of its outputs (the means).
std::string EncoderScript(const ConvShape& shape, int latents) {
  std::string src =
      "    x = self.leaky(torch.conv2d(x, self.encoder_stem_weight, self.encoder_stem_bias, [1, 1], [1, 1], "
      "[1, 1], 1))\n";
  for (int i = 0; i < shape.levels; ++i) {
    src += absl::StrCat("    x = self.leaky(torch.conv2d(x, self.encoder_down", i, "_weight, self.encoder_down", i,
                        "_bias, [2, 2], [1, 1], [1, 1], 1))\n");
  }
  src += "    x = torch.linear(x.flatten(1), self.encoder_head_weight, self.encoder_head_bias)\n";
  return src + absl::StrCat("    return x[:, :", latents, "]\n");
}

// TorchScript's source of the net (the same operations as the modules above, by aten's names: the C++ compiler of
// TorchScript resolves torch.* builtins, not torch.nn.functional). Parameters are attributes named by their path,
// dots as underscores.
std::string ScriptSource(const GeometryVaeOptions& o) {
  std::string src = DecodeScript(ShapeOf(o));
  src += "    return self.mean + self.scale * x\n";
  src += R"(
def forward(self, z: Tensor) -> Tensor:
    return self.decode(z)

def encode(self, maps: Tensor, valid: Tensor) -> Tensor:
    b = maps.size(0)
    n = valid.sum([2, 3]).clamp_min(1.0)
    map_centre = (maps * valid).sum([2, 3]) / n
    mean_centre = (self.mean * valid).sum([2, 3]) / n
    p = ((maps - map_centre.view(b, 3, 1, 1)) * valid).view(b, 3, -1)
    m = ((self.mean - mean_centre.view(b, 3, 1, 1)) * valid).view(b, 3, -1)
    u, s, vh = torch.linalg_svd(torch.bmm(m, p.transpose(1, 2)), False)
    d = torch.sign(torch.linalg_det(torch.bmm(u, vh)))
    flip = torch.stack([torch.ones_like(d), torch.ones_like(d), d], 1)
    r = torch.bmm(u * flip.unsqueeze(1), vh)
    aligned = torch.einsum("bij,bjhw->bihw", [r, maps - map_centre.view(b, 3, 1, 1)]) + mean_centre.view(b, 3, 1, 1)
    x = torch.cat([(aligned - self.mean) / self.scale * valid, valid], 1)
)";
  return src + EncoderScript(ShapeOf(o), o.geometry_latent + o.pose_latent);
}

// `net`'s parameters and buffers (dots in their names as underscores) with `source`'s methods, as a TorchScript
// module named `name` written atomically to `path`.
absl::Status ExportScript(const torch::nn::Module& net, const char* name, const std::string& source,
                          const std::string& path, const char* what) {
  try {
    torch::NoGradGuard no_grad;
    torch::jit::Module script(name);
    auto attribute = [](std::string n) {
      std::replace(n.begin(), n.end(), '.', '_');
      return n;
    };
    for (const auto& p : net.named_parameters()) {
      script.register_parameter(attribute(p.key()), p.value().detach().clone(), /*is_buffer=*/false);
    }
    for (const auto& b : net.named_buffers()) script.register_buffer(attribute(b.key()), b.value().clone());
    script.define(source);
    const std::string tmp = path + ".tmp";
    script.save(tmp);
    std::error_code ec;
    std::filesystem::rename(tmp, path, ec);
    if (ec) return absl::UnavailableError(absl::StrCat(path, ": ", ec.message()));
    return absl::OkStatus();
  } catch (const std::exception& e) {
    return internal::TorchError(what, absl::StrCat("exporting ", path), e);
  }
}

}  // namespace

absl::Status TorchGeometryVae::ExportTorchScript(const std::string& path) const {
  return ExportScript(*impl_->net, "FaStageGeometryVae", ScriptSource(impl_->options), path, kNet);
}

absl::Status TorchGeometryVae::Load(const std::string& path) {
  return LoadArchive(*impl_->net, *impl_->adam, path, kNet);
}

namespace {

constexpr const char* kExpressionNet = "expression VAE";

struct ExpressionNetImpl : torch::nn::Module {
  explicit ExpressionNetImpl(const ExpressionVaeOptions& o)
      : latents(o.expression_latent + o.view_latent), expression(o.expression_latent) {
    encoder = register_module("encoder", Encoder(ShapeOf(o), 1, 2 * latents));
    // The decoder's input: both latents and the indicator (0 for the performer).
    decoder = register_module("decoder", Decoder(ShapeOf(o), latents + 1, 1));
  }
  // Means and log-variances of images (B x 1 x I x I, 0..1; centred on 0.5 for the net).
  std::pair<torch::Tensor, torch::Tensor> Encode(const torch::Tensor& images) {
    const torch::Tensor stats = encoder->forward(images - 0.5);
    return {stats.slice(1, 0, latents), stats.slice(1, latents, 2 * latents).clamp(-10, 10)};
  }
  torch::Tensor Decode(const torch::Tensor& z) {
    return decoder->forward(torch::cat({z, torch::zeros({z.size(0), 1})}, 1)) + 0.5;
  }
  // [expression of a | view of b].
  torch::Tensor Mix(const torch::Tensor& a, const torch::Tensor& b) {
    return torch::cat({a.slice(1, 0, expression), b.slice(1, expression, latents)}, 1);
  }
  int latents, expression;
  Encoder encoder{nullptr};
  Decoder decoder{nullptr};
};
TORCH_MODULE(ExpressionNet);

}  // namespace

struct ExpressionVaeState {
  ExpressionVaeOptions options;
  ExpressionNet net{nullptr};
  std::unique_ptr<torch::optim::Adam> adam;
  int64_t latents() const { return options.expression_latent + options.view_latent; }
  int64_t pixels() const { return static_cast<int64_t>(options.input_size) * options.input_size; }
};

class TorchExpressionVae final : public internal::ExpressionVaeNet {
 public:
  explicit TorchExpressionVae(std::unique_ptr<ExpressionVaeState> impl) : impl_(std::move(impl)) {}
  absl::StatusOr<ExpressionLosses> TrainStep(const ExpressionBatch& batch, double learning_rate) override;
  absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& images, int batch) const override;
  absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& latents, int batch) const override;
  absl::Status Save(const std::string& path) const override;
  absl::Status Load(const std::string& path) override;
  const ExpressionVaeOptions& options() const override;
  int64_t parameter_count() const override;
  std::unique_ptr<ExpressionVaeState> impl_;
};
const ExpressionVaeOptions& TorchExpressionVae::options() const { return impl_->options; }

int64_t TorchExpressionVae::parameter_count() const { return CountParameters(*impl_->net); }

absl::StatusOr<std::unique_ptr<internal::ExpressionVaeNet>> internal::MakeExpressionVae(
    const ExpressionVaeOptions& options) {
  try {
    internal::SetThreads(options.threads);
    auto impl = std::make_unique<ExpressionVaeState>();
    impl->options = options;
    impl->net = internal::Seeded(options.seed, [&] { return ExpressionNet(options); });
    impl->adam = std::make_unique<torch::optim::Adam>(impl->net->parameters(), torch::optim::AdamOptions(1e-3));
    return std::unique_ptr<internal::ExpressionVaeNet>(new TorchExpressionVae(std::move(impl)));
  } catch (const std::exception& e) {
    return internal::TorchError(kExpressionNet, "creating the net", e);
  }
}

absl::StatusOr<ExpressionLosses> TorchExpressionVae::TrainStep(const ExpressionBatch& batch, double learning_rate) {
  const ExpressionVaeOptions& o = impl_->options;
  const int64_t b = batch.batch, s = o.input_size, l = impl_->latents();
  if (b < 1) return absl::InvalidArgumentError(absl::StrCat(kExpressionNet, ": an empty batch"));
  for (auto [v, n, what] : {std::tuple{&batch.anchor, b * impl_->pixels(), "the anchors"},
                            std::tuple{&batch.same_expression, b * impl_->pixels(), "the same expressions"},
                            std::tuple{&batch.same_view, b * impl_->pixels(), "the same views"},
                            std::tuple{&batch.noise, 3 * b * l, "the noise"}}) {
    if (auto st = CheckSize(*v, n, what, kExpressionNet); !st.ok()) return st;
  }
  try {
    internal::SetThreads(o.threads);
    ExpressionNet& net = impl_->net;
    net->train();
    SetLearningRate(*impl_->adam, learning_rate);
    impl_->adam->zero_grad();
    // The three images as one batch: anchors, same expressions, same views.
    const torch::Tensor images =
        torch::cat({FromVector(batch.anchor, {b, 1, s, s}), FromVector(batch.same_expression, {b, 1, s, s}),
                    FromVector(batch.same_view, {b, 1, s, s})});
    const auto [mu, logvar] = net->Encode(images);
    const torch::Tensor z = mu + FromVector(batch.noise, {3 * b, l}) * torch::exp(0.5 * logvar);
    const torch::Tensor anchor = images.slice(0, 0, b);
    const torch::Tensor z_anchor = z.slice(0, 0, b), z_expression = z.slice(0, b, 2 * b), z_view = z.slice(0, 2 * b);
    const torch::Tensor reconstruction = (net->Decode(z) - images).pow(2).mean();
    const torch::Tensor expression_swap = (net->Decode(net->Mix(z_expression, z_anchor)) - anchor).pow(2).mean();
    const torch::Tensor view_swap = (net->Decode(net->Mix(z_anchor, z_view)) - anchor).pow(2).mean();
    // Frame b's expression seen from the other camera: encoded again, the two latents come back. Not computed when
    // its weight is 0 (the default: a decode and an encode of a batch's anchors saved).
    torch::Tensor cycle = torch::zeros({});
    if (o.cycle_weight > 0) {
      const torch::Tensor crossed = net->Mix(mu.slice(0, 2 * b), mu.slice(0, b, 2 * b));
      cycle = (net->Encode(net->Decode(crossed)).first - crossed.detach()).pow(2).mean();
    }
    const torch::Tensor kl = Kl(mu, logvar);
    const torch::Tensor total =
        reconstruction + o.swap_weight * (expression_swap + view_swap) + o.cycle_weight * cycle + o.kl_weight * kl;
    total.backward();
    impl_->adam->step();
    return ExpressionLosses{total.item<double>(),     reconstruction.item<double>(), expression_swap.item<double>(),
                            view_swap.item<double>(), cycle.item<double>(),          kl.item<double>()};
  } catch (const std::exception& e) {
    return internal::TorchError(kExpressionNet, "training", e);
  }
}

absl::StatusOr<std::vector<float>> TorchExpressionVae::Encode(const std::vector<float>& images, int batch) const {
  const int64_t s = impl_->options.input_size;
  if (auto st = CheckSize(images, batch * impl_->pixels(), "the images", kExpressionNet); !st.ok()) return st;
  try {
    internal::SetThreads(impl_->options.threads);
    torch::NoGradGuard no_grad;
    impl_->net->eval();
    return ToVector(impl_->net->Encode(FromVector(images, {batch, 1, s, s})).first);
  } catch (const std::exception& e) {
    return internal::TorchError(kExpressionNet, "encoding", e);
  }
}

absl::StatusOr<std::vector<float>> TorchExpressionVae::Decode(const std::vector<float>& latents, int batch) const {
  if (auto st = CheckSize(latents, batch * impl_->latents(), "the latents", kExpressionNet); !st.ok()) return st;
  try {
    internal::SetThreads(impl_->options.threads);
    torch::NoGradGuard no_grad;
    impl_->net->eval();
    return ToVector(impl_->net->Decode(FromVector(latents, {batch, impl_->latents()})));
  } catch (const std::exception& e) {
    return internal::TorchError(kExpressionNet, "decoding", e);
  }
}

absl::Status TorchExpressionVae::Save(const std::string& path) const {
  return SaveArchive(*impl_->net, *impl_->adam, path, kExpressionNet);
}

absl::Status TorchExpressionVae::Load(const std::string& path) {
  return LoadArchive(*impl_->net, *impl_->adam, path, kExpressionNet);
}

namespace {

constexpr const char* kMappingNet = "latent mapping";

struct MappingNetImpl : torch::nn::Module {
  MappingNetImpl(const LatentMappingOptions& o, const torch::Tensor& mean, const torch::Tensor& scale) {
    for (int i = 0; i < o.layers; ++i) {
      const int in = i == 0 ? o.input : o.hidden, out = i + 1 == o.layers ? o.output : o.hidden;
      layers.push_back(register_module(absl::StrCat("linear", i), torch::nn::Linear(in, out)));
    }
    target_mean = register_buffer("target_mean", mean);
    target_scale = register_buffer("target_scale", scale);
  }
  // The normalized targets' prediction.
  torch::Tensor forward(torch::Tensor x) {
    for (size_t i = 0; i < layers.size(); ++i) {
      x = layers[i]->forward(x);
      if (i + 1 < layers.size()) x = Leaky(x);
    }
    return x;
  }
  std::vector<torch::nn::Linear> layers;
  torch::Tensor target_mean, target_scale;
};
TORCH_MODULE(MappingNet);

}  // namespace

struct LatentMappingState {
  LatentMappingOptions options;
  MappingNet net{nullptr};
  std::unique_ptr<torch::optim::Adam> adam;
};

class TorchLatentMapping final : public internal::LatentMappingNet {
 public:
  explicit TorchLatentMapping(std::unique_ptr<LatentMappingState> impl) : impl_(std::move(impl)) {}
  absl::StatusOr<double> TrainStep(const std::vector<float>& inputs, const std::vector<float>& targets,
                                   const std::vector<float>& noise, int batch, double learning_rate) override;
  absl::StatusOr<std::vector<float>> Map(const std::vector<float>& inputs, int batch) const override;
  absl::Status Save(const std::string& path) const override;
  absl::Status Load(const std::string& path) override;
  const LatentMappingOptions& options() const override;
  int64_t parameter_count() const override;
  std::unique_ptr<LatentMappingState> impl_;
};
const LatentMappingOptions& TorchLatentMapping::options() const { return impl_->options; }
int64_t TorchLatentMapping::parameter_count() const { return CountParameters(*impl_->net); }

absl::StatusOr<std::unique_ptr<internal::LatentMappingNet>> internal::MakeLatentMapping(
    const LatentMappingOptions& options, const std::vector<float>& target_mean,
    const std::vector<float>& target_scale) {
  if (auto s = CheckSize(target_mean, options.output, "the targets' mean", kMappingNet); !s.ok()) return s;
  if (auto s = CheckSize(target_scale, options.output, "the targets' scale", kMappingNet); !s.ok()) return s;
  if (*std::min_element(target_scale.begin(), target_scale.end()) <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(kMappingNet, ": a target's scale is not positive"));
  }
  try {
    internal::SetThreads(options.threads);
    auto impl = std::make_unique<LatentMappingState>();
    impl->options = options;
    impl->net = internal::Seeded(options.seed, [&] {
      return MappingNet(options, FromVector(target_mean, {1, options.output}),
                        FromVector(target_scale, {1, options.output}));
    });
    impl->adam = std::make_unique<torch::optim::Adam>(impl->net->parameters(), torch::optim::AdamOptions(1e-3));
    return std::unique_ptr<internal::LatentMappingNet>(new TorchLatentMapping(std::move(impl)));
  } catch (const std::exception& e) {
    return internal::TorchError(kMappingNet, "creating the net", e);
  }
}

absl::StatusOr<double> TorchLatentMapping::TrainStep(const std::vector<float>& inputs,
                                                     const std::vector<float>& targets, const std::vector<float>& noise,
                                                     int batch, double learning_rate) {
  const LatentMappingOptions& o = impl_->options;
  if (batch < 1) return absl::InvalidArgumentError(absl::StrCat(kMappingNet, ": an empty batch"));
  for (auto [v, n, what] : {std::tuple{&inputs, int64_t{batch} * o.input, "the inputs"},
                            std::tuple{&targets, int64_t{batch} * o.output, "the targets"},
                            std::tuple{&noise, int64_t{batch} * o.input, "the noise"}}) {
    if (auto st = CheckSize(*v, n, what, kMappingNet); !st.ok()) return st;
  }
  try {
    internal::SetThreads(o.threads);
    MappingNet& net = impl_->net;
    net->train();
    SetLearningRate(*impl_->adam, learning_rate);
    impl_->adam->zero_grad();
    const torch::Tensor x = FromVector(inputs, {batch, o.input}) + FromVector(noise, {batch, o.input});
    const torch::Tensor y = (FromVector(targets, {batch, o.output}) - net->target_mean) / net->target_scale;
    const torch::Tensor loss = (net->forward(x) - y).pow(2).mean();
    loss.backward();
    impl_->adam->step();
    return loss.item<double>();
  } catch (const std::exception& e) {
    return internal::TorchError(kMappingNet, "training", e);
  }
}

absl::StatusOr<std::vector<float>> TorchLatentMapping::Map(const std::vector<float>& inputs, int batch) const {
  const LatentMappingOptions& o = impl_->options;
  STAGE_RETURN_IF_ERROR(CheckSize(inputs, int64_t{batch} * o.input, "the inputs", kMappingNet));
  try {
    internal::SetThreads(o.threads);
    torch::NoGradGuard no_grad;
    MappingNet& net = impl_->net;
    net->eval();
    return ToVector(net->target_mean + net->target_scale * net->forward(FromVector(inputs, {batch, o.input})));
  } catch (const std::exception& e) {
    return internal::TorchError(kMappingNet, "mapping", e);
  }
}

absl::Status TorchLatentMapping::Save(const std::string& path) const {
  return SaveArchive(*impl_->net, *impl_->adam, path, kMappingNet);
}

absl::Status TorchLatentMapping::Load(const std::string& path) {
  return LoadArchive(*impl_->net, *impl_->adam, path, kMappingNet);
}

namespace {

constexpr const char* kDrivingNet = "driving net";

// The expression encoder and the mapping, as DrivingNet trains them.
struct DrivingModuleImpl : torch::nn::Module {
  DrivingModuleImpl(const ExpressionVaeOptions& e, const LatentMappingOptions& m, const torch::Tensor& mean,
                    const torch::Tensor& scale)
      : expression(e.expression_latent) {
    encoder = register_module("encoder", Encoder(ShapeOf(e), 1, 2 * (e.expression_latent + e.view_latent)));
    mapping = register_module("mapping", MappingNet(m, mean, scale));
  }
  // The normalized geometry latents of crops (0..1).
  torch::Tensor forward(const torch::Tensor& images) {
    return mapping->forward(encoder->forward(images - 0.5).slice(1, 0, expression));
  }
  int expression;
  Encoder encoder{nullptr};
  MappingNet mapping{nullptr};
};
TORCH_MODULE(DrivingModule);

// `to`'s parameters and buffers set to `from`'s of the same names (the same architecture).
void CopyWeights(const torch::nn::Module& from, torch::nn::Module& to) {
  torch::NoGradGuard no_grad;
  auto source = from.named_parameters();
  for (auto& p : to.named_parameters()) p.value().copy_(source[p.key()]);
  auto buffers = from.named_buffers();
  for (auto& b : to.named_buffers()) b.value().copy_(buffers[b.key()]);
}

}  // namespace

struct DrivingNetState {
  DrivingNetOptions options;
  int input_size = 0;
  DrivingModule net{nullptr};
  std::unique_ptr<torch::optim::Adam> adam;
  // UseMapLoss's: the geometry VAE's decoder (a frozen copy) and the texels' weights (1 x 1 x S x S); empty: none.
  Decoder map_decoder{nullptr};
  torch::Tensor map_weights;
  std::vector<torch::Tensor> Trained() const {
    return options.train_encoder ? net->parameters() : net->mapping->parameters();
  }
};

class TorchDrivingNet final : public internal::DrivingNetNet {
 public:
  explicit TorchDrivingNet(std::unique_ptr<DrivingNetState> impl) : impl_(std::move(impl)) {}
  absl::StatusOr<double> TrainStep(const std::vector<float>& images, const std::vector<float>& targets, int batch,
                                   double learning_rate) override;
  absl::Status UseMapLoss(const internal::GeometryVaeNet& geometry, const std::vector<float>& weights) override;
  absl::StatusOr<std::vector<float>> Drive(const std::vector<float>& images, int batch) const override;
  absl::Status Save(const std::string& path) const override;
  absl::Status Load(const std::string& path) override;
  const DrivingNetOptions& options() const override;
  int input_size() const override;
  int output() const override;
  int64_t trained_parameters() const override;
  std::unique_ptr<DrivingNetState> impl_;
};
const DrivingNetOptions& TorchDrivingNet::options() const { return impl_->options; }
int TorchDrivingNet::input_size() const { return impl_->input_size; }
int TorchDrivingNet::output() const { return static_cast<int>(impl_->net->mapping->target_mean.size(1)); }

int64_t TorchDrivingNet::trained_parameters() const {
  int64_t n = 0;
  for (const auto& p : impl_->Trained()) n += p.numel();
  return n;
}

absl::StatusOr<std::unique_ptr<internal::DrivingNetNet>> internal::MakeDrivingNet(
    const internal::ExpressionVaeNet& expression_net, const internal::LatentMappingNet& mapping_net,
    const DrivingNetOptions& options) {
  const auto& expression = static_cast<const TorchExpressionVae&>(expression_net);
  const auto& mapping = static_cast<const TorchLatentMapping&>(mapping_net);
  const ExpressionVaeOptions& eo = expression.options();
  if (mapping.options().input != eo.expression_latent) {
    return absl::InvalidArgumentError(absl::StrCat(kDrivingNet, ": the mapping takes ", mapping.options().input,
                                                   " numbers, the expression latent has ", eo.expression_latent));
  }
  try {
    internal::SetThreads(options.threads);
    auto impl = std::make_unique<DrivingNetState>();
    impl->options = options;
    impl->input_size = eo.input_size;
    const MappingNet& m = mapping.impl_->net;
    impl->net = DrivingModule(eo, mapping.options(), m->target_mean.clone(), m->target_scale.clone());
    CopyWeights(*expression.impl_->net->encoder, *impl->net->encoder);
    CopyWeights(*m, *impl->net->mapping);
    for (auto& p : impl->net->encoder->parameters()) p.set_requires_grad(options.train_encoder);
    impl->adam = std::make_unique<torch::optim::Adam>(impl->Trained(), torch::optim::AdamOptions(1e-4));
    return std::unique_ptr<internal::DrivingNetNet>(new TorchDrivingNet(std::move(impl)));
  } catch (const std::exception& e) {
    return internal::TorchError(kDrivingNet, "creating the net", e);
  }
}

absl::StatusOr<double> TorchDrivingNet::TrainStep(const std::vector<float>& images, const std::vector<float>& targets,
                                                  int batch, double learning_rate) {
  const int64_t s = impl_->input_size, out = output();
  if (batch < 1) return absl::InvalidArgumentError(absl::StrCat(kDrivingNet, ": an empty batch"));
  if (auto st = CheckSize(images, batch * s * s, "the images", kDrivingNet); !st.ok()) return st;
  if (auto st = CheckSize(targets, batch * out, "the targets", kDrivingNet); !st.ok()) return st;
  try {
    internal::SetThreads(impl_->options.threads);
    DrivingModule& net = impl_->net;
    net->train();
    SetLearningRate(*impl_->adam, learning_rate);
    impl_->adam->zero_grad();
    const torch::Tensor y =
        (FromVector(targets, {batch, out}) - net->mapping->target_mean) / net->mapping->target_scale;
    const torch::Tensor driven = net->forward(FromVector(images, {batch, 1, s, s}));
    torch::Tensor loss;
    if (impl_->map_decoder) {
      // Both latents back in the geometry VAE's units, decoded; the target's map needs no gradient.
      const torch::Tensor& mean = net->mapping->target_mean;
      const torch::Tensor& scale = net->mapping->target_scale;
      torch::Tensor target_map;
      {
        torch::NoGradGuard no_grad;
        target_map = impl_->map_decoder->forward(y * scale + mean);
      }
      const torch::Tensor& w = impl_->map_weights;
      loss = MaskedMse(impl_->map_decoder->forward(driven * scale + mean), target_map, w.expand({batch, 1, -1, -1}));
    } else {
      // Each dimension weighed by its variance (the mapping's normalization undone, over the mean variance): a latent
      // dimension the geometry VAE barely uses does not count as much as one that moves the face.
      const torch::Tensor variance = net->mapping->target_scale.pow(2);
      const torch::Tensor weight = variance / variance.mean();
      loss = ((driven - y).pow(2) * weight).mean();
    }
    loss.backward();
    impl_->adam->step();
    return loss.item<double>();
  } catch (const std::exception& e) {
    return internal::TorchError(kDrivingNet, "training", e);
  }
}

absl::Status TorchDrivingNet::UseMapLoss(const internal::GeometryVaeNet& geometry_net,
                                         const std::vector<float>& weights) {
  const auto& geometry = static_cast<const TorchGeometryVae&>(geometry_net);
  const GeometryVaeOptions& g = geometry.options();
  if (g.geometry_latent != output()) {
    return absl::InvalidArgumentError(absl::StrCat(kDrivingNet, ": the geometry VAE's latent has ", g.geometry_latent,
                                                   " numbers, the mapping gives ", output()));
  }
  const int64_t s = g.input_size;
  if (auto st = CheckSize(weights, s * s, "the texels' weights", kDrivingNet); !st.ok()) return st;
  try {
    impl_->map_decoder = Decoder(ShapeOf(g), g.geometry_latent, 3);
    CopyWeights(*geometry.impl_->net->decoder, *impl_->map_decoder);
    for (auto& p : impl_->map_decoder->parameters()) p.set_requires_grad(false);
    impl_->map_decoder->eval();
    impl_->map_weights = FromVector(weights, {1, 1, s, s});
    return absl::OkStatus();
  } catch (const std::exception& e) {
    return internal::TorchError(kDrivingNet, "taking the geometry VAE's decoder", e);
  }
}

absl::StatusOr<std::vector<float>> TorchDrivingNet::Drive(const std::vector<float>& images, int batch) const {
  const int64_t s = impl_->input_size;
  if (auto st = CheckSize(images, batch * s * s, "the images", kDrivingNet); !st.ok()) return st;
  try {
    internal::SetThreads(impl_->options.threads);
    torch::NoGradGuard no_grad;
    DrivingModule& net = impl_->net;
    net->eval();
    const torch::Tensor y = net->forward(FromVector(images, {batch, 1, s, s}));
    return ToVector(y * net->mapping->target_scale + net->mapping->target_mean);
  } catch (const std::exception& e) {
    return internal::TorchError(kDrivingNet, "driving", e);
  }
}

absl::Status TorchDrivingNet::Save(const std::string& path) const {
  return SaveArchive(*impl_->net, *impl_->adam, path, kDrivingNet);
}

absl::Status TorchDrivingNet::Load(const std::string& path) {
  return LoadArchive(*impl_->net, *impl_->adam, path, kDrivingNet);
}

// The texture VAE.
namespace {

constexpr const char* kTextureNet = "texture VAE";

struct TextureNetImpl : torch::nn::Module {
  TextureNetImpl(const TextureVaeOptions& o, const torch::Tensor& neutral_textures, const torch::Tensor& spread)
      : latent(o.texture_latent) {
    encoder = register_module("encoder", Encoder(ShapeOf(o), o.channels + 1, 2 * o.texture_latent));
    decoder = register_module("decoder", Decoder(ShapeOf(o), o.texture_latent, o.channels));
    neutral = register_buffer("neutral", neutral_textures);
    scale = register_buffer("scale", spread);
  }
  // The latent's means and log-variances of textures (B x C x S x S) and validity (B x 1 x S x S).
  std::pair<torch::Tensor, torch::Tensor> Stats(const torch::Tensor& textures, const torch::Tensor& valid) {
    const torch::Tensor out = encoder->forward(torch::cat({(textures - neutral) / scale * valid, valid}, 1));
    return {out.slice(1, 0, latent), out.slice(1, latent, 2 * latent).clamp(-10, 10)};
  }
  int latent;
  Encoder encoder{nullptr};
  Decoder decoder{nullptr};
  torch::Tensor neutral, scale;
};
TORCH_MODULE(TextureNet);

}  // namespace

struct TextureVaeState {
  TextureVaeOptions options;
  TextureNet net{nullptr};
  std::unique_ptr<torch::optim::Adam> adam;
  int64_t texels() const { return static_cast<int64_t>(options.input_size) * options.input_size; }
};

class TorchTextureVae final : public internal::TextureVaeNet {
 public:
  explicit TorchTextureVae(std::unique_ptr<TextureVaeState> impl) : impl_(std::move(impl)) {}
  absl::StatusOr<TextureLosses> TrainStep(const TextureBatch& batch, double learning_rate) override;
  absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& textures, const std::vector<float>& valid,
                                            int batch) const override;
  absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& latents, int batch) const override;
  absl::Status Save(const std::string& path) const override;
  absl::Status Load(const std::string& path) override;
  absl::Status ExportTorchScript(const std::string& path) const override;
  const TextureVaeOptions& options() const override;
  int64_t parameter_count() const override;
  std::unique_ptr<TextureVaeState> impl_;
};
const TextureVaeOptions& TorchTextureVae::options() const { return impl_->options; }
int64_t TorchTextureVae::parameter_count() const { return CountParameters(*impl_->net); }

absl::StatusOr<std::unique_ptr<internal::TextureVaeNet>> internal::MakeTextureVae(const TextureVaeOptions& options,
                                                                                  const std::vector<float>& neutral,
                                                                                  const std::vector<float>& scale) {
  const int64_t s = options.input_size, c = options.channels;
  STAGE_RETURN_IF_ERROR(CheckSize(neutral, c * s * s, "the neutral textures", kTextureNet));
  STAGE_RETURN_IF_ERROR(CheckSize(scale, c, "the spread", kTextureNet));
  for (float x : scale) {
    if (!(x > 0)) return absl::InvalidArgumentError(absl::StrCat(kTextureNet, ": a spread of ", x, " is not positive"));
  }
  try {
    internal::SetThreads(options.threads);
    auto impl = std::make_unique<TextureVaeState>();
    impl->options = options;
    impl->net = internal::Seeded(options.seed, [&] {
      return TextureNet(options, FromVector(neutral, {1, c, s, s}), FromVector(scale, {1, c, 1, 1}));
    });
    impl->adam = std::make_unique<torch::optim::Adam>(impl->net->parameters(), torch::optim::AdamOptions(1e-3));
    return std::unique_ptr<internal::TextureVaeNet>(new TorchTextureVae(std::move(impl)));
  } catch (const std::exception& e) {
    return internal::TorchError(kTextureNet, "creating the net", e);
  }
}

absl::StatusOr<TextureLosses> TorchTextureVae::TrainStep(const TextureBatch& batch, double learning_rate) {
  const TextureVaeOptions& o = impl_->options;
  const int64_t b = batch.batch, s = o.input_size, c = o.channels;
  if (b < 1) return absl::InvalidArgumentError(absl::StrCat(kTextureNet, ": an empty batch"));
  STAGE_RETURN_IF_ERROR(CheckSize(batch.textures, b * c * s * s, "the textures", kTextureNet));
  STAGE_RETURN_IF_ERROR(CheckSize(batch.valid, b * s * s, "the validity", kTextureNet));
  STAGE_RETURN_IF_ERROR(CheckSize(batch.noise, b * o.texture_latent, "the noise", kTextureNet));
  try {
    internal::SetThreads(o.threads);
    TextureNet& net = impl_->net;
    net->train();
    SetLearningRate(*impl_->adam, learning_rate);
    const torch::Tensor textures = FromVector(batch.textures, {b, c, s, s});
    const torch::Tensor valid = FromVector(batch.valid, {b, 1, s, s});
    impl_->adam->zero_grad();
    const auto [mu, logvar] = net->Stats(textures, valid);
    const torch::Tensor z = mu + FromVector(batch.noise, {b, o.texture_latent}) * torch::exp(0.5 * logvar);
    const torch::Tensor decoded = net->decoder->forward(z);  // normalized wrinkle maps
    const torch::Tensor target = (textures - net->neutral) / net->scale;
    const torch::Tensor reconstruction = ((decoded - target).pow(2) * valid).sum() / (c * valid.sum()).clamp_min(1);
    const torch::Tensor kl = Kl(mu, logvar);
    const torch::Tensor total = reconstruction + o.kl_weight * kl;
    total.backward();
    impl_->adam->step();
    return TextureLosses{total.item<double>(), reconstruction.item<double>(), kl.item<double>()};
  } catch (const std::exception& e) {
    return internal::TorchError(kTextureNet, "training", e);
  }
}

absl::StatusOr<std::vector<float>> TorchTextureVae::Encode(const std::vector<float>& textures,
                                                           const std::vector<float>& valid, int batch) const {
  const TextureVaeOptions& o = impl_->options;
  const int64_t s = o.input_size;
  STAGE_RETURN_IF_ERROR(
      CheckSize(textures, int64_t{batch} * o.channels * impl_->texels(), "the textures", kTextureNet));
  STAGE_RETURN_IF_ERROR(CheckSize(valid, int64_t{batch} * impl_->texels(), "the validity", kTextureNet));
  try {
    internal::SetThreads(o.threads);
    torch::NoGradGuard no_grad;
    impl_->net->eval();
    return ToVector(
        impl_->net->Stats(FromVector(textures, {batch, o.channels, s, s}), FromVector(valid, {batch, 1, s, s})).first);
  } catch (const std::exception& e) {
    return internal::TorchError(kTextureNet, "encoding", e);
  }
}

absl::StatusOr<std::vector<float>> TorchTextureVae::Decode(const std::vector<float>& latents, int batch) const {
  const TextureVaeOptions& o = impl_->options;
  STAGE_RETURN_IF_ERROR(CheckSize(latents, int64_t{batch} * o.texture_latent, "the texture latents", kTextureNet));
  try {
    internal::SetThreads(o.threads);
    torch::NoGradGuard no_grad;
    impl_->net->eval();
    const torch::Tensor d = impl_->net->decoder->forward(FromVector(latents, {batch, o.texture_latent}));
    return ToVector(impl_->net->neutral + impl_->net->scale * d);
  } catch (const std::exception& e) {
    return internal::TorchError(kTextureNet, "decoding", e);
  }
}

absl::Status TorchTextureVae::Save(const std::string& path) const {
  return SaveArchive(*impl_->net, *impl_->adam, path, kTextureNet);
}

absl::Status TorchTextureVae::ExportTorchScript(const std::string& path) const {
  const TextureVaeOptions& o = impl_->options;
  std::string src = DecodeScript(ShapeOf(o));
  src += "    return self.neutral + self.scale * x\n";
  src += R"(
def forward(self, z: Tensor) -> Tensor:
    return self.decode(z)

def encode(self, textures: Tensor, valid: Tensor) -> Tensor:
    x = torch.cat([(textures - self.neutral) / self.scale * valid, valid], 1)
)";
  src += EncoderScript(ShapeOf(o), o.texture_latent);
  return ExportScript(*impl_->net, "FaStageTextureVae", src, path, kTextureNet);
}

absl::Status TorchTextureVae::Load(const std::string& path) {
  return LoadArchive(*impl_->net, *impl_->adam, path, kTextureNet);
}

absl::StatusOr<double> internal::ConvFloor(int size, int channels, int batch, int steps, int threads) {
  try {
    internal::SetThreads(threads);
    auto [conv, x] = internal::Seeded(1, [&] {
      return std::pair{torch::nn::Conv2d(torch::nn::Conv2dOptions(channels, channels, 3).padding(1)),
                       torch::randn({batch, channels, size, size})};
    });
    auto step = [&] {
      conv->zero_grad();
      conv->forward(x).square().mean().backward();
    };
    step();  // warm-up
    const auto start = std::chrono::steady_clock::now();
    for (int i = 0; i < steps; ++i) step();
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    const double macs = 3.0 * batch * size * size * channels * channels * 9 * steps;
    return macs / seconds;
  } catch (const std::exception& e) {
    return internal::TorchError("conv floor", "timing", e);
  }
}

}  // namespace stage::processing
