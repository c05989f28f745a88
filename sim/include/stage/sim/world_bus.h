// stage-sim's world bus as a slot clock, from outside the world: a gRPC client of SimWorld's Run, EndRun and GetRun
// that names who asks. Two drivers use it: a sync generator light node of the simulated stage (its clock line is the
// bus) and stage-controller on a rig that names no generator (the world's own bus). Links no renderer.
#pragma once

#include <chrono>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/v1/sim.grpc.pb.h"

namespace stage::sim {

class WorldBus {
 public:
  // `caller` names who drives the bus (a light node's id, or "controller"): the world records it with the runs.
  WorldBus(const std::string& address, std::string caller);

  const std::string& address() const { return address_; }
  // Plans (plan_only) or starts a run; asked again while the world is slow to answer, up to `give_up`.
  absl::StatusOr<v1::WorldRunReply> Run(v1::RunWorldRequest request, std::chrono::steady_clock::time_point give_up);
  absl::StatusOr<v1::WorldRunReply> End(int64_t align_slots);
  absl::StatusOr<v1::WorldRunReply> Get();

 private:
  std::string address_, caller_;
  std::unique_ptr<v1::SimWorld::Stub> world_;
};

}  // namespace stage::sim
