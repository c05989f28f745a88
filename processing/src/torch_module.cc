// The torch module's entry point (torch_nets.h): the one symbol libstage_torch_nets.so exports.
#include "torch_nets.h"
#include "torch_support.h"

namespace stage::processing::internal {
namespace {

const TorchHost* host = nullptr;  // set once, by the entry point, before any net is made

}  // namespace

void Warn(const std::string& message) {
  if (host != nullptr && host->warn != nullptr) host->warn(message);
}

}  // namespace stage::processing::internal

extern "C" __attribute__((visibility("default"))) const stage::processing::internal::TorchNets* StageTorchNets(
    const stage::processing::internal::TorchHost* host) {
  namespace internal = stage::processing::internal;
  internal::host = host;
  static const internal::TorchNets nets{
      .abi = internal::kTorchNetsAbi,
      .geometry_vae = &internal::MakeGeometryVae,
      .texture_vae = &internal::MakeTextureVae,
      .expression_vae = &internal::MakeExpressionVae,
      .latent_mapping = &internal::MakeLatentMapping,
      .driving_net = &internal::MakeDrivingNet,
      .warp_net = &internal::MakeWarpNet,
      .set_threads = &internal::SetThreads,
      .blas_library = &internal::BlasLibrary,
      .conv_floor = &internal::ConvFloor,
  };
  return &nets;
}
