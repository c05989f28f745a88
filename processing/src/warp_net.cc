// The stabilization's self-supervised U-Net (docs/assets.md#the-u-net) and torch's process-wide settings, in the torch
// module (torch_nets.h): the rest sees warp_net.h.
#include <ATen/Parallel.h>
#include <dlfcn.h>
#include <malloc.h>
#include <torch/torch.h>

#include <algorithm>
#include <mutex>
#include <new>
#include <random>
#include <string>
#include <thread>

#include "absl/strings/str_cat.h"
#include "torch_nets.h"
#include "torch_support.h"

// OpenBLAS, linked ahead of the reference BLAS Debian's libtorch names (processing/CMakeLists.txt).
extern "C" void openblas_set_num_threads(int threads);

namespace stage::processing {
namespace {

namespace nnf = torch::nn::functional;

// A warp of 1 (the head's output) moves this many texels: the net starts at 0 and reaches a few texels quickly.
constexpr double kFlowGain = 4.0;
constexpr double kCharbonnierEps = 0.01;
// The photometric loss of a reference texel the warp takes off the frame's coverage (log-luminance: a large residual).
constexpr double kOffCoveragePenalty = 0.3;

torch::nn::Conv2d Conv(int in, int out) { return torch::nn::Conv2d(torch::nn::Conv2dOptions(in, out, 3).padding(1)); }

torch::Tensor LeakyRelu(const torch::Tensor& x) {
  return nnf::leaky_relu(x, nnf::LeakyReLUFuncOptions().negative_slope(0.1));
}

// Two 3 x 3 convolutions, each with a leaky ReLU.
struct BlockImpl : torch::nn::Module {
  BlockImpl(int in, int out) : a(register_module("a", Conv(in, out))), b(register_module("b", Conv(out, out))) {}
  torch::Tensor forward(const torch::Tensor& x) { return LeakyRelu(b(LeakyRelu(a(x)))); }
  torch::nn::Conv2d a, b;
};
TORCH_MODULE(Block);

// The U-Net: the input's 2 x 2 blocks folded into channels (pixel unshuffle: every texel kept, the convolutions at
// half the resolution, 4x cheaper), `levels` blocks down (average pooling between them), back up (bilinear
// upsampling, the skip concatenated), a 3 x 3 head to the warp (2 channels) and the wrinkle map (1) of each texel of
// the 2 x 2 block, unfolded back. The head starts at zero: no warp, no wrinkle, until the losses ask for them.
struct UNetImpl : torch::nn::Module {
  UNetImpl(int levels, int base) {
    std::vector<int> channels;
    int in = 6 * 4;  // the frame's log-luminance and coverage, the reference's, the base warp; of 2 x 2 texels
    for (int l = 0; l < levels; ++l) {
      channels.push_back(base << l);
      down.push_back(register_module(absl::StrCat("down", l), Block(in, channels.back())));
      in = channels.back();
    }
    for (int l = 0; l + 1 < levels; ++l) {
      up.push_back(register_module(absl::StrCat("up", l), Block(channels[l + 1] + channels[l], channels[l])));
    }
    head = register_module("head", Conv(base, 3 * 4));
    torch::NoGradGuard no_grad;
    head->weight.zero_();
    head->bias.zero_();
  }

  torch::Tensor forward(torch::Tensor x) {
    x = torch::pixel_unshuffle(x, 2);
    std::vector<torch::Tensor> skips;
    for (size_t l = 0; l < down.size(); ++l) {
      x = down[l]->forward(x);
      skips.push_back(x);
      if (l + 1 < down.size()) x = nnf::avg_pool2d(x, nnf::AvgPool2dFuncOptions(2));
    }
    for (size_t l = up.size(); l-- > 0;) {
      x = nnf::interpolate(x, nnf::InterpolateFuncOptions()
                                  .size(std::vector<int64_t>{skips[l].size(2), skips[l].size(3)})
                                  .mode(torch::kBilinear)
                                  .align_corners(false));
      x = up[l]->forward(torch::cat({x, skips[l]}, 1));
    }
    return torch::pixel_shuffle(head(x), 2);
  }

  std::vector<Block> down, up;
  torch::nn::Conv2d head{nullptr};
};
TORCH_MODULE(UNet);

// An image of the net's inputs (2 channels: value, coverage) as a 1 x 2 x H x W tensor.
torch::Tensor ToTensor(const Image& image) {
  return torch::from_blob(const_cast<float*>(image.pixels.data()), {image.height, image.width, image.channels},
                          torch::kFloat32)
      .permute({2, 0, 1})
      .unsqueeze(0)
      .clone();
}

Image ToImage(const torch::Tensor& t) {  // 1 x C x H x W
  const torch::Tensor hwc = t.squeeze(0).permute({1, 2, 0}).contiguous();
  Image out(static_cast<int>(hwc.size(1)), static_cast<int>(hwc.size(0)), static_cast<int>(hwc.size(2)));
  std::copy_n(hwc.data_ptr<float>(), out.pixels.size(), out.pixels.data());
  return out;
}

// `image` (N x C x H x W) sampled at each texel plus `flow` (N x 2 x H x W, texels); 0 outside.
torch::Tensor Warp(const torch::Tensor& image, const torch::Tensor& flow) {
  const int64_t h = flow.size(2), w = flow.size(3);
  const auto options = torch::TensorOptions().dtype(torch::kFloat32);
  const torch::Tensor xs = torch::arange(w, options).view({1, 1, w}), ys = torch::arange(h, options).view({1, h, 1});
  const torch::Tensor gx = (xs + flow.select(1, 0)) * (2.0 / std::max<int64_t>(1, w - 1)) - 1;
  const torch::Tensor gy = (ys + flow.select(1, 1)) * (2.0 / std::max<int64_t>(1, h - 1)) - 1;
  return nnf::grid_sample(
      image, torch::stack({gx, gy}, 3),
      nnf::GridSampleFuncOptions().mode(torch::kBilinear).padding_mode(torch::kZeros).align_corners(true));
}

torch::Tensor Charbonnier(const torch::Tensor& r) { return (r.pow(2) + kCharbonnierEps * kCharbonnierEps).sqrt(); }

// A torch exception (c10::Error, std::bad_alloc) as a status: nothing of torch's throws past this file.
torch::Tensor Pool(const torch::Tensor& t, int64_t k) {
  return k == 1 ? t : nnf::avg_pool2d(t, nnf::AvgPool2dFuncOptions(k).stride(k));
}

torch::Tensor GradientSquared(const torch::Tensor& t) {
  const int64_t h = t.size(2), w = t.size(3);
  const torch::Tensor dx = t.narrow(3, 1, w - 1) - t.narrow(3, 0, w - 1);
  const torch::Tensor dy = t.narrow(2, 1, h - 1) - t.narrow(2, 0, h - 1);
  return dx.pow(2).mean() + dy.pow(2).mean();
}

torch::Tensor GradientAbs(const torch::Tensor& t) {
  const int64_t h = t.size(2), w = t.size(3);
  return (t.narrow(3, 1, w - 1) - t.narrow(3, 0, w - 1)).abs().mean() +
         (t.narrow(2, 1, h - 1) - t.narrow(2, 0, h - 1)).abs().mean();
}

}  // namespace

namespace internal {

absl::Status TorchError(const std::string& net, const std::string& doing, const std::exception& e) {
  const std::string what = e.what();
  const std::string first_line = what.substr(0, what.find('\n'));
  if (dynamic_cast<const std::bad_alloc*>(&e) != nullptr || first_line.find("alloc") != std::string::npos) {
    return absl::ResourceExhaustedError(absl::StrCat(net, ": out of memory ", doing, ": ", first_line));
  }
  return absl::InternalError(absl::StrCat(net, ": ", doing, ": ", first_line));
}

std::mutex& TorchSeedMutex() {
  static std::mutex mutex;
  return mutex;
}

void SeedTorch(uint64_t seed) { torch::manual_seed(seed); }

}  // namespace internal

int internal::SetThreads(int threads) {
  const int n = ThreadCount(threads);
  static std::once_flag once;
  std::call_once(once, [] {
    if (const std::string blas = BlasLibrary(); blas.find("openblas") == std::string::npos) {
      Warn(absl::StrCat("torch's BLAS is ", blas.empty() ? "missing" : blas,
                        ", not OpenBLAS (see processing/CMakeLists.txt's link order): training runs slower"));
    }
    at::set_num_interop_threads(1);
    // Torch's own loops are the parallelism; a BLAS call inside one runs on its thread.
    openblas_set_num_threads(1);
    // glibc's malloc moves its mmap and trim thresholds with the sizes freed: past some 10000 steps of a fine-tuning
    // each step's tensors came to be handed back to the kernel and faulted in again (38,000 page faults a second, a
    // quarter of the time in the kernel, steps three times slower; docs/asset.md#speed). Fixed thresholds keep them
    // in the heap.
    mallopt(M_MMAP_THRESHOLD, 64 << 20);
    mallopt(M_TRIM_THRESHOLD, 256 << 20);
  });
  at::set_num_threads(n);
  return n;
}

std::string internal::BlasLibrary() {
  void* sgemm = dlsym(RTLD_DEFAULT, "sgemm_");
  Dl_info info;
  if (sgemm == nullptr || dladdr(sgemm, &info) == 0 || info.dli_fname == nullptr) return "";
  return info.dli_fname;
}

struct WarpNetState {
  WarpNetOptions options;
  UNet net{nullptr};
  std::vector<double> losses;
  bool with_bases = false;  // trained with base warps

  // The net's input (1 x 6 x H x W) for a frame and the reference: log-luminances about the reference's covered mean,
  // in units of its standard deviation (the skin's contrast is a few percent: unscaled, the net barely learns), 0
  // where not covered.
  // The base warp enters in units of the head's gain.
  static torch::Tensor Input(const torch::Tensor& frame, const torch::Tensor& reference, const torch::Tensor& base) {
    const torch::Tensor rc = reference.narrow(1, 1, 1), fc = frame.narrow(1, 1, 1), rv = reference.narrow(1, 0, 1);
    const torch::Tensor count = rc.sum().clamp_min(1);
    const torch::Tensor mean = (rv * rc).sum() / count;
    const torch::Tensor scale = 1 / ((rv - mean).pow(2) * rc).sum().div(count).sqrt().clamp_min(1e-3);
    return torch::cat({(frame.narrow(1, 0, 1) - mean) * fc * scale, fc, (rv - mean) * rc * scale, rc, base / kFlowGain},
                      1);
  }

  // The net's warp (base + its correction) and wrinkle map for a frame.
  std::pair<torch::Tensor, torch::Tensor> Run(const torch::Tensor& frame, const torch::Tensor& reference,
                                              const torch::Tensor& base) {
    const torch::Tensor out = net->forward(Input(frame, reference, base));
    return {base + out.narrow(1, 0, 2) * kFlowGain, out.narrow(1, 2, 1)};
  }

  // The losses for one frame; `out` is the net's output for it. The warp answers to what the wrinkle map leaves (its
  // gradient stops at the map, so the map cannot explain away a misalignment), the wrinkle map to what the warp leaves
  // (its gradient stops at the warp), at the net's full resolution.
  torch::Tensor Loss(const torch::Tensor& frame, const torch::Tensor& reference, const torch::Tensor& flow,
                     const torch::Tensor& wrinkle) const {
    // Where coverage is partial the warp's gradient (its divisor, the warped coverage, held constant) sees the holes
    // at log-luminance 0. Centring the values on the reference's mean instead measured worse on the simulated
    // performance (still-skin jitter 0.98 % against 0.90 %), so they stay as they are.
    const torch::Tensor fc = frame.narrow(1, 1, 1), rc = reference.narrow(1, 1, 1);
    const torch::Tensor fv = frame.narrow(1, 0, 1) * fc, rv = reference.narrow(1, 0, 1) * rc;
    torch::Tensor photometric = torch::zeros({}, torch::kFloat32), wrinkle_fit;
    for (int s = 0; s < options.loss_scales; ++s) {
      const int64_t k = int64_t{1} << s;
      if (frame.size(2) / k < 4) break;
      const torch::Tensor ref_c = Pool(rc, k), ref_v = Pool(rv, k) / ref_c.clamp_min(1e-3);
      const torch::Tensor warped =
          Warp(torch::cat({Pool(fv, k), Pool(fc, k)}, 1), Pool(flow, k) / static_cast<double>(k));
      const torch::Tensor warped_c = warped.narrow(1, 1, 1);
      const torch::Tensor warped_v = warped.narrow(1, 0, 1) / warped_c.clamp_min(1e-3).detach();
      // Where the reference is covered: the residual where the warp lands on covered texels, a fixed penalty where
      // it leaves them (else leaving the coverage would be the loss's cheapest way out).
      const torch::Tensor ref_valid = (ref_c > 0.999).to(torch::kFloat32).detach();
      const torch::Tensor landed = warped_c.clamp(0, 1);
      const torch::Tensor residual = warped_v - ref_v - Pool(wrinkle, k).detach();
      const torch::Tensor per_texel = landed * Charbonnier(residual) + (1 - landed) * kOffCoveragePenalty;
      photometric = photometric + (per_texel * ref_valid).sum() / ref_valid.sum().clamp_min(1);
      if (s == 0) {
        const torch::Tensor valid = ref_valid * (warped_c > 0.999).to(torch::kFloat32).detach();
        wrinkle_fit = (Charbonnier(warped_v.detach() - ref_v - wrinkle) * valid).sum() / valid.sum().clamp_min(1);
      }
    }
    return photometric + options.smoothness * GradientSquared(flow) + wrinkle_fit +
           options.wrinkle_sparsity * wrinkle.abs().mean() + options.wrinkle_smoothness * GradientAbs(wrinkle);
  }
};

class TorchWarpNet final : public internal::WarpNetNet {
 public:
  explicit TorchWarpNet(std::unique_ptr<WarpNetState> impl) : impl_(std::move(impl)) {}
  absl::Status Train(const Image& reference, const std::vector<Image>& frames, const std::vector<Image>& bases,
                     const std::function<bool(int step, double loss)>& step) override;
  absl::StatusOr<WarpNetPrediction> Predict(const Image& reference, const Image& frame,
                                            const Image& base) const override;
  const std::vector<double>& losses() const override;
  std::unique_ptr<WarpNetState> impl_;
};

absl::StatusOr<std::unique_ptr<internal::WarpNetNet>> internal::MakeWarpNet(const WarpNetOptions& options) {
  try {
    internal::SetThreads(options.threads);
    auto impl = std::make_unique<WarpNetState>();
    impl->options = options;
    impl->net = internal::Seeded(options.seed, [&] { return UNet(options.levels, options.base_channels); });
    return std::unique_ptr<internal::WarpNetNet>(new TorchWarpNet(std::move(impl)));
  } catch (const std::exception& e) {
    return internal::TorchError("warp net", "creating the net", e);
  }
}

namespace {

absl::Status CheckInput(const Image& image, const Image& reference, int levels, const std::string& what,
                        const char* channels = "log-luminance, coverage") {
  if (image.channels != 2) {
    return absl::InvalidArgumentError(
        absl::StrCat("warp net: ", what, " has ", image.channels, " channel(s), not 2 (", channels, ")"));
  }
  if (image.pixels.size() != static_cast<size_t>(image.width) * image.height * 2) {
    return absl::InvalidArgumentError(absl::StrCat("warp net: ", what, " holds ", image.pixels.size(), " values, not ",
                                                   image.width, " x ", image.height, " x 2"));
  }
  if (image.width != reference.width || image.height != reference.height) {
    return absl::InvalidArgumentError(absl::StrCat("warp net: ", what, " is ", image.width, " x ", image.height,
                                                   ", the reference ", reference.width, " x ", reference.height));
  }
  const int step = 1 << levels;
  if (image.width < 2 * step || image.height < 2 * step || image.width % step != 0 || image.height % step != 0) {
    return absl::InvalidArgumentError(absl::StrCat("warp net: ", what, ": ", image.width, " x ", image.height,
                                                   " does not divide by 2^levels = ", step, " at least twice"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status TorchWarpNet::Train(const Image& reference, const std::vector<Image>& frames,
                                 const std::vector<Image>& bases, const std::function<bool(int, double)>& progress) {
  const WarpNetOptions& o = impl_->options;
  if (frames.empty()) return absl::InvalidArgumentError("warp net: no frames to train on");
  if (!bases.empty() && bases.size() != frames.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("warp net: ", bases.size(), " base warp(s) for ", frames.size(), " frame(s)"));
  }
  if (auto s = CheckInput(reference, reference, o.levels, "the reference"); !s.ok()) return s;
  try {
    std::vector<torch::Tensor> inputs, base_tensors;
    for (size_t i = 0; i < frames.size(); ++i) {
      if (auto s = CheckInput(frames[i], reference, o.levels, absl::StrCat("frame ", i)); !s.ok()) return s;
      inputs.push_back(ToTensor(frames[i]));
      if (!bases.empty()) {
        if (auto s = CheckInput(bases[i], reference, o.levels, absl::StrCat("base warp ", i), "x, y"); !s.ok())
          return s;
      }
      base_tensors.push_back(bases.empty() ? torch::zeros({1, 2, reference.height, reference.width})
                                           : ToTensor(bases[i]));
    }
    impl_->with_bases = !bases.empty();
    internal::SetThreads(o.threads);
    const torch::Tensor ref = ToTensor(reference);
    impl_->net->train();
    torch::optim::Adam adam(impl_->net->parameters(), torch::optim::AdamOptions(o.learning_rate));
    std::mt19937_64 rng(o.seed);
    for (int step = 0; step < o.iterations; ++step) {
      // The last 30 % of the steps at a fifth of the rate.
      if (step == o.iterations * 7 / 10) {
        for (auto& group : adam.param_groups()) {
          static_cast<torch::optim::AdamOptions&>(group.options()).lr(o.learning_rate / 5);
        }
      }
      const size_t i = rng() % inputs.size();
      adam.zero_grad();
      const auto [flow, wrinkle] = impl_->Run(inputs[i], ref, base_tensors[i]);
      const torch::Tensor loss = impl_->Loss(inputs[i], ref, flow, wrinkle);
      loss.backward();
      adam.step();
      impl_->losses.push_back(loss.item<double>());
      if (progress && !progress(step, impl_->losses.back())) {
        return absl::CancelledError(absl::StrCat("warp net: training cancelled after ", step + 1, " step(s)"));
      }
    }
    return absl::OkStatus();
  } catch (const std::exception& e) {
    return internal::TorchError("warp net", "training", e);
  }
}

absl::StatusOr<WarpNetPrediction> TorchWarpNet::Predict(const Image& reference, const Image& frame,
                                                        const Image& base) const {
  if (auto s = CheckInput(reference, reference, impl_->options.levels, "the reference"); !s.ok()) return s;
  if (auto s = CheckInput(frame, reference, impl_->options.levels, "the frame"); !s.ok()) return s;
  const bool has_base = base.width > 0;
  if (has_base != impl_->with_bases) {
    return absl::InvalidArgumentError(has_base ? "warp net: a base warp for a net trained without them"
                                               : "warp net: no base warp for a net trained with them");
  }
  if (has_base) {
    if (auto s = CheckInput(base, reference, impl_->options.levels, "the base warp", "x, y"); !s.ok()) return s;
  }
  try {
    internal::SetThreads(impl_->options.threads);
    torch::NoGradGuard no_grad;
    impl_->net->eval();
    const torch::Tensor b = has_base ? ToTensor(base) : torch::zeros({1, 2, reference.height, reference.width});
    const auto [flow, wrinkle] = impl_->Run(ToTensor(frame), ToTensor(reference), b);
    return WarpNetPrediction{ToImage(flow), ToImage(wrinkle)};
  } catch (const std::exception& e) {
    return internal::TorchError("warp net", "predicting", e);
  }
}

const std::vector<double>& TorchWarpNet::losses() const { return impl_->losses; }

}  // namespace stage::processing
