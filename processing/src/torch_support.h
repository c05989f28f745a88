// What the processing library's torch sources (warp_net.cc, asset_net.cc) share, without torch's headers: torch's
// exceptions turned into statuses, and the lock about torch's process-wide random generator.
#pragma once

#include <exception>
#include <mutex>
#include <string>

#include "absl/status/status.h"

namespace stage::processing::internal {

// ResourceExhausted for an allocation that failed, else Internal: "<net>: <doing>: <the exception's first line>".
absl::Status TorchError(const std::string& net, const std::string& doing, const std::exception& e);

// Held while seeding torch's generator and drawing a net's weights: a worker's concurrent jobs must not draw between
// another's seeding and its weights.
std::mutex& TorchSeedMutex();

}  // namespace stage::processing::internal
