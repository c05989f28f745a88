// The simulated world as the controller's sync generator and as a take's ground truth: a gRPC client of stage-sim's
// SimWorld service (its Run, EndRun, GetRun and WriteGroundTruth). Links no renderer: stage-controller registers it
// when it is told the world's address (--sim-world).
#pragma once

#include <memory>
#include <string>

#include "sync_generator.h"

namespace stage::sim {

// The world's bus as the slot clock of takes.
std::unique_ptr<controller::SyncGenerator> NewWorldSyncGenerator(const std::string& world_address);
// The world's ground truth of a take's frames.
std::unique_ptr<controller::TakeTruth> NewWorldTakeTruth(const std::string& world_address);

}  // namespace stage::sim
