// What the torch module's sources (warp_net.cc, asset_net.cc, torch_module.cc) share, without torch's headers: their
// factories and settings, which the module's entry point gathers; torch's exceptions turned into statuses; nets drawn
// under the lock about torch's process-wide random generator.
#pragma once

#include <cstdint>
#include <exception>
#include <mutex>
#include <string>

#include "absl/status/status.h"
#include "torch_nets.h"

namespace stage::processing::internal {

// The factories of TorchNets (torch_nets.h), for options already validated.
absl::StatusOr<std::unique_ptr<GeometryVaeNet>> MakeGeometryVae(const GeometryVaeOptions& options,
                                                                const std::vector<float>& mean, float scale);
absl::StatusOr<std::unique_ptr<TextureVaeNet>> MakeTextureVae(const TextureVaeOptions& options,
                                                              const std::vector<float>& neutral,
                                                              const std::vector<float>& scale);
absl::StatusOr<std::unique_ptr<ExpressionVaeNet>> MakeExpressionVae(const ExpressionVaeOptions& options);
absl::StatusOr<std::unique_ptr<LatentMappingNet>> MakeLatentMapping(const LatentMappingOptions& options,
                                                                    const std::vector<float>& target_mean,
                                                                    const std::vector<float>& target_scale);
// `expression` and `mapping` are the module's own.
absl::StatusOr<std::unique_ptr<DrivingNetNet>> MakeDrivingNet(const ExpressionVaeNet& expression,
                                                              const LatentMappingNet& mapping,
                                                              const DrivingNetOptions& options);
absl::StatusOr<std::unique_ptr<WarpNetNet>> MakeWarpNet(const WarpNetOptions& options);

// SetTorchThreads, TorchBlasLibrary and ConvFloorMacsPerSecond (its arguments checked) of warp_net.h and asset_net.h.
int SetThreads(int threads);
std::string BlasLibrary();
absl::StatusOr<double> ConvFloor(int size, int channels, int batch, int steps, int threads);

// A warning through the programs' loggers (TorchHost).
void Warn(const std::string& message);

// ResourceExhausted for an allocation that failed, else Internal: "<net>: <doing>: <the exception's first line>".
absl::Status TorchError(const std::string& net, const std::string& doing, const std::exception& e);

// Torch's generator is the process's: a worker's concurrent jobs must not draw between another's seeding and its
// weights. `make()` (a net's construction, which draws its weights) runs with the generator seeded by `seed`, under
// one lock.
void SeedTorch(uint64_t seed);  // defined beside the torch sources
std::mutex& TorchSeedMutex();
template <typename Make>
auto Seeded(uint64_t seed, Make make) {
  std::lock_guard<std::mutex> lock(TorchSeedMutex());
  SeedTorch(seed);
  return make();
}

}  // namespace stage::processing::internal
