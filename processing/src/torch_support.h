// What the processing library's torch sources (warp_net.cc, asset_net.cc) share, without torch's headers: torch's
// exceptions turned into statuses, and nets drawn under the lock about torch's process-wide random generator.
#pragma once

#include <cstdint>
#include <exception>
#include <mutex>
#include <string>

#include "absl/status/status.h"

namespace stage::processing::internal {

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
