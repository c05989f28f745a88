// The nets' public classes (asset_net.h, warp_net.h) in front of the torch module (torch_nets.h): their options'
// checks, and every call forwarded to the module, which is opened the first time a net is made.
#include "torch_nets.h"

#include "stage/common/logging.h"
#include "stage/common/module.h"
#include "stage/common/status.h"

namespace stage::processing {
namespace internal {
namespace {

void WarnFromTorch(const std::string& message) { Logger("processing.torch")->warn("{}", message); }

absl::StatusOr<const TorchNets*> OpenTorchNets() {
  const ModuleSpec spec{.target = kTorchNetsTarget, .entry = kTorchNetsEntry, .what = "the torch nets' module"};
  STAGE_ASSIGN_OR_RETURN(void* entry, OpenModule(spec));
  static const TorchHost host{&WarnFromTorch};
  const TorchNets* nets = reinterpret_cast<TorchNetsEntry>(entry)(&host);
  if (nets == nullptr || nets->abi != kTorchNetsAbi) {
    return absl::FailedPreconditionError(absl::StrCat("the torch nets' module ", ModulePath(spec),
                                                      ": interface version ", nets == nullptr ? 0 : nets->abi, ", not ",
                                                      kTorchNetsAbi, " (a module of another build)"));
  }
  return nets;  // never closed: torch's threads and registrations live as long as the process
}

}  // namespace

absl::StatusOr<const TorchNets*> LoadTorchNets() {
  static const absl::StatusOr<const TorchNets*> nets = OpenTorchNets();
  return nets;
}

}  // namespace internal

using internal::ConvShape;
using internal::ShapeOf;
using internal::ValidateShape;

namespace {

template <typename Bad>
absl::Status CheckThreads(int threads, Bad bad) {
  if (threads < 0) return bad(absl::StrCat("threads ", threads, " is negative"));
  return absl::OkStatus();
}

}  // namespace

// ---- options --------------------------------------------------------------------------------------------------------

absl::Status GeometryVaeOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("geometry VAE: ", what)); };
  STAGE_RETURN_IF_ERROR(ValidateShape(ShapeOf(*this), bad));
  if (geometry_latent < 1 || geometry_latent > 1024) return bad(absl::StrCat("geometry latent ", geometry_latent));
  if (pose_latent < 1 || pose_latent > 64) return bad(absl::StrCat("pose latent ", pose_latent, " is not in 1..64"));
  if (!(kl_weight >= 0)) return bad(absl::StrCat("KL weight ", kl_weight, " is negative"));
  return CheckThreads(threads, bad);
}

absl::Status ExpressionVaeOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("expression VAE: ", what)); };
  STAGE_RETURN_IF_ERROR(ValidateShape(ShapeOf(*this), bad));
  if (expression_latent < 1 || expression_latent > 1024) {
    return bad(absl::StrCat("expression latent ", expression_latent, " is not in 1..1024"));
  }
  if (view_latent < 1 || view_latent > 64) return bad(absl::StrCat("view latent ", view_latent, " is not in 1..64"));
  if (!(kl_weight >= 0) || !(swap_weight >= 0) || !(cycle_weight >= 0)) return bad("a loss weight is negative");
  return CheckThreads(threads, bad);
}

absl::Status LatentMappingOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("latent mapping: ", what)); };
  if (input < 1 || input > 1024 || output < 1 || output > 1024) {
    return bad(absl::StrCat("sizes ", input, " -> ", output, " are not in 1..1024"));
  }
  if (hidden < 8 || hidden > 4096) return bad(absl::StrCat("hidden units ", hidden, " are not in 8..4096"));
  if (layers < 2 || layers > 8) return bad(absl::StrCat("layers ", layers, " are not in 2..8"));
  return CheckThreads(threads, bad);
}

absl::Status DrivingNetOptions::Validate() const {
  return CheckThreads(
      threads, [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("driving net: ", what)); });
}

absl::Status TextureVaeOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("texture VAE: ", what)); };
  STAGE_RETURN_IF_ERROR(ValidateShape(ShapeOf(*this), bad));
  if (channels < 1 || channels > 16) return bad(absl::StrCat("channels ", channels, " is not in 1..16"));
  if (texture_latent < 1 || texture_latent > 1024) {
    return bad(absl::StrCat("texture latent ", texture_latent, " is not in 1..1024"));
  }
  if (!(kl_weight >= 0)) return bad(absl::StrCat("KL weight ", kl_weight, " is negative"));
  return CheckThreads(threads, bad);
}

absl::Status WarpNetOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("warp net: ", what)); };
  if (levels < 2 || levels > 6) return bad(absl::StrCat("levels ", levels, " is not in 2..6"));
  if (base_channels < 4 || base_channels > 64) {
    return bad(absl::StrCat("base_channels ", base_channels, " is not in 4..64"));
  }
  if (iterations < 1 || iterations > 100000)
    return bad(absl::StrCat("iterations ", iterations, " is not in 1..100000"));
  if (!(learning_rate > 0) || learning_rate > 1) {
    return bad(absl::StrCat("learning_rate ", learning_rate, " is not in (0, 1]"));
  }
  if (loss_scales < 1 || loss_scales > 6) return bad(absl::StrCat("loss_scales ", loss_scales, " is not in 1..6"));
  if (!(smoothness >= 0)) return bad(absl::StrCat("smoothness ", smoothness, " is below 0"));
  if (!(wrinkle_sparsity >= 0)) return bad(absl::StrCat("wrinkle_sparsity ", wrinkle_sparsity, " is below 0"));
  if (!(wrinkle_smoothness >= 0)) return bad(absl::StrCat("wrinkle_smoothness ", wrinkle_smoothness, " is below 0"));
  if (threads < 0 || threads > 256) return bad(absl::StrCat("threads ", threads, " is not in 0..256"));
  return absl::OkStatus();
}

// ---- the nets -------------------------------------------------------------------------------------------------------

absl::StatusOr<std::unique_ptr<GeometryVae>> GeometryVae::Create(const GeometryVaeOptions& options,
                                                                 const std::vector<float>& mean, float scale) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, nets->geometry_vae(options, mean, scale));
  return std::unique_ptr<GeometryVae>(new GeometryVae(std::move(impl)));
}
GeometryVae::GeometryVae(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
GeometryVae::~GeometryVae() = default;
absl::StatusOr<GeometryLosses> GeometryVae::TrainStep(const GeometryBatch& batch, double learning_rate) {
  return impl_->TrainStep(batch, learning_rate);
}
absl::StatusOr<std::vector<float>> GeometryVae::Encode(const std::vector<float>& maps, const std::vector<float>& valid,
                                                       int batch) const {
  return impl_->Encode(maps, valid, batch);
}
absl::StatusOr<std::vector<float>> GeometryVae::Decode(const std::vector<float>& geometry_latents, int batch) const {
  return impl_->Decode(geometry_latents, batch);
}
absl::StatusOr<std::vector<float>> GeometryVae::Reposed(const std::vector<float>& maps, const std::vector<float>& valid,
                                                        int batch) const {
  return impl_->Reposed(maps, valid, batch);
}
absl::Status GeometryVae::Save(const std::string& path) const { return impl_->Save(path); }
absl::Status GeometryVae::Load(const std::string& path) { return impl_->Load(path); }
absl::Status GeometryVae::ExportTorchScript(const std::string& path) const { return impl_->ExportTorchScript(path); }
const GeometryVaeOptions& GeometryVae::options() const { return impl_->options(); }
int64_t GeometryVae::parameter_count() const { return impl_->parameter_count(); }

absl::StatusOr<std::unique_ptr<TextureVae>> TextureVae::Create(const TextureVaeOptions& options,
                                                               const std::vector<float>& neutral,
                                                               const std::vector<float>& scale) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, nets->texture_vae(options, neutral, scale));
  return std::unique_ptr<TextureVae>(new TextureVae(std::move(impl)));
}
TextureVae::TextureVae(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
TextureVae::~TextureVae() = default;
absl::StatusOr<TextureLosses> TextureVae::TrainStep(const TextureBatch& batch, double learning_rate) {
  return impl_->TrainStep(batch, learning_rate);
}
absl::StatusOr<std::vector<float>> TextureVae::Encode(const std::vector<float>& textures,
                                                      const std::vector<float>& valid, int batch) const {
  return impl_->Encode(textures, valid, batch);
}
absl::StatusOr<std::vector<float>> TextureVae::Decode(const std::vector<float>& latents, int batch) const {
  return impl_->Decode(latents, batch);
}
absl::Status TextureVae::Save(const std::string& path) const { return impl_->Save(path); }
absl::Status TextureVae::Load(const std::string& path) { return impl_->Load(path); }
absl::Status TextureVae::ExportTorchScript(const std::string& path) const { return impl_->ExportTorchScript(path); }
const TextureVaeOptions& TextureVae::options() const { return impl_->options(); }
int64_t TextureVae::parameter_count() const { return impl_->parameter_count(); }

absl::StatusOr<std::unique_ptr<ExpressionVae>> ExpressionVae::Create(const ExpressionVaeOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, nets->expression_vae(options));
  return std::unique_ptr<ExpressionVae>(new ExpressionVae(std::move(impl)));
}
ExpressionVae::ExpressionVae(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
ExpressionVae::~ExpressionVae() = default;
absl::StatusOr<ExpressionLosses> ExpressionVae::TrainStep(const ExpressionBatch& batch, double learning_rate) {
  return impl_->TrainStep(batch, learning_rate);
}
absl::StatusOr<std::vector<float>> ExpressionVae::Encode(const std::vector<float>& images, int batch) const {
  return impl_->Encode(images, batch);
}
absl::StatusOr<std::vector<float>> ExpressionVae::Decode(const std::vector<float>& latents, int batch) const {
  return impl_->Decode(latents, batch);
}
absl::Status ExpressionVae::Save(const std::string& path) const { return impl_->Save(path); }
absl::Status ExpressionVae::Load(const std::string& path) { return impl_->Load(path); }
const ExpressionVaeOptions& ExpressionVae::options() const { return impl_->options(); }
int64_t ExpressionVae::parameter_count() const { return impl_->parameter_count(); }

absl::StatusOr<std::unique_ptr<LatentMapping>> LatentMapping::Create(const LatentMappingOptions& options,
                                                                     const std::vector<float>& target_mean,
                                                                     const std::vector<float>& target_scale) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, nets->latent_mapping(options, target_mean, target_scale));
  return std::unique_ptr<LatentMapping>(new LatentMapping(std::move(impl)));
}
LatentMapping::LatentMapping(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
LatentMapping::~LatentMapping() = default;
absl::StatusOr<double> LatentMapping::TrainStep(const std::vector<float>& inputs, const std::vector<float>& targets,
                                                const std::vector<float>& noise, int batch, double learning_rate) {
  return impl_->TrainStep(inputs, targets, noise, batch, learning_rate);
}
absl::StatusOr<std::vector<float>> LatentMapping::Map(const std::vector<float>& inputs, int batch) const {
  return impl_->Map(inputs, batch);
}
absl::Status LatentMapping::Save(const std::string& path) const { return impl_->Save(path); }
absl::Status LatentMapping::Load(const std::string& path) { return impl_->Load(path); }
const LatentMappingOptions& LatentMapping::options() const { return impl_->options(); }
int64_t LatentMapping::parameter_count() const { return impl_->parameter_count(); }

absl::StatusOr<std::unique_ptr<DrivingNet>> DrivingNet::Create(const ExpressionVae& expression,
                                                               const LatentMapping& mapping,
                                                               const DrivingNetOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, nets->driving_net(*expression.impl_, *mapping.impl_, options));
  return std::unique_ptr<DrivingNet>(new DrivingNet(std::move(impl)));
}
DrivingNet::DrivingNet(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
DrivingNet::~DrivingNet() = default;
absl::StatusOr<double> DrivingNet::TrainStep(const std::vector<float>& images, const std::vector<float>& targets,
                                             int batch, double learning_rate) {
  return impl_->TrainStep(images, targets, batch, learning_rate);
}
absl::Status DrivingNet::UseMapLoss(const GeometryVae& geometry, const std::vector<float>& weights) {
  return impl_->UseMapLoss(*geometry.impl_, weights);
}
absl::StatusOr<std::vector<float>> DrivingNet::Drive(const std::vector<float>& images, int batch) const {
  return impl_->Drive(images, batch);
}
absl::Status DrivingNet::Save(const std::string& path) const { return impl_->Save(path); }
absl::Status DrivingNet::Load(const std::string& path) { return impl_->Load(path); }
const DrivingNetOptions& DrivingNet::options() const { return impl_->options(); }
int DrivingNet::input_size() const { return impl_->input_size(); }
int DrivingNet::output() const { return impl_->output(); }
int64_t DrivingNet::trained_parameters() const { return impl_->trained_parameters(); }

absl::StatusOr<std::unique_ptr<WarpNet>> WarpNet::Create(const WarpNetOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, nets->warp_net(options));
  return std::unique_ptr<WarpNet>(new WarpNet(std::move(impl)));
}
WarpNet::WarpNet(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
WarpNet::~WarpNet() = default;
absl::Status WarpNet::Train(const Image& reference, const std::vector<Image>& frames, const std::vector<Image>& bases,
                            const std::function<bool(int step, double loss)>& step) {
  return impl_->Train(reference, frames, bases, step);
}
absl::StatusOr<WarpNetPrediction> WarpNet::Predict(const Image& reference, const Image& frame,
                                                   const Image& base) const {
  return impl_->Predict(reference, frame, base);
}
const std::vector<double>& WarpNet::losses() const { return impl_->losses(); }

// ---- torch's settings and figures -----------------------------------------------------------------------------------

int TorchThreadCount(int threads) { return internal::ThreadCount(threads); }

int SetTorchThreads(int threads) {
  auto nets = internal::LoadTorchNets();
  if (!nets.ok()) {
    Logger("processing.torch")->error("{}", nets.status().message());
    return TorchThreadCount(threads);  // nothing runs torch in this process: the count it would have used
  }
  return (*nets)->set_threads(threads);
}

std::string TorchBlasLibrary() {
  auto nets = internal::LoadTorchNets();
  return nets.ok() ? (*nets)->blas_library() : "";
}

absl::StatusOr<double> ConvFloorMacsPerSecond(int size, int channels, int batch, int steps, int threads) {
  if (size < 4 || channels < 1 || batch < 1 || steps < 1) {
    return absl::InvalidArgumentError("conv floor: size, channels, batch and steps must be positive");
  }
  STAGE_ASSIGN_OR_RETURN(const internal::TorchNets* nets, internal::LoadTorchNets());
  return nets->conv_floor(size, channels, batch, steps, threads);
}

double GeometryVaeForwardMacs(const GeometryVaeOptions& o) {
  const ConvShape shape = ShapeOf(o);
  auto channels = [&](int level) { return static_cast<double>(shape.Channels(level)); };
  const double s = o.input_size;
  double macs = s * s * 4 * channels(0) * 9;  // the stem
  for (int i = 0; i < o.levels; ++i) {
    const double r = s / (2 << i);  // each stride-2 level's output
    macs += r * r * channels(i) * channels(i + 1) * 9;
  }
  const double side = o.input_size >> o.levels, top = channels(o.levels) * side * side;
  macs += top * 2 * (o.geometry_latent + o.pose_latent);  // the encoder's head
  macs += o.geometry_latent * top;                        // the decoder's input
  for (int i = o.levels - 1; i >= 0; --i) {
    const double r = s / (1 << i);
    macs += r * r * channels(i + 1) * channels(i) * 9;
  }
  macs += s * s * channels(0) * 3 * 9;  // the decoder's output
  return macs + o.pose_latent * 64 + 64 * 9;
}

}  // namespace stage::processing
