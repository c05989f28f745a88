// How simulated devices reach the world: in the same process (LocalWorldClient) or in stage-sim's SimWorld service
// over gRPC (ConnectWorld). The sim light driver and the sim camera use only this interface.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/sim/world.h"

namespace stage::sim {

class WorldClient {
 public:
  virtual ~WorldClient() = default;
  // Joins as `name` (a light node gives its index in the rig, a camera -1); the device number for the calls below.
  virtual absl::StatusOr<int> Join(const std::string& name, int light_node) = 0;
  // The world's rate, mode and t0 (valid after Join).
  virtual uint32_t slot_rate_hz() const = 0;
  virtual bool lockstep() const = 0;
  virtual int64_t t0_ns() const = 0;
  // As World's; nullopt when the world stopped or cannot be reached.
  virtual std::optional<WorldEdge> WaitForEdge(int device, int64_t slot) = 0;
  virtual void Done(int device, int64_t slot) = 0;
  virtual void ReportLevels(int light_node, int64_t t_ns, const std::vector<double>& levels, int64_t watermark_ns) = 0;
  // As World's: Cancelled when the world stopped (or cannot be reached), OutOfRange when too old.
  virtual absl::StatusOr<EmitterLevels> Exposure(int64_t t0_ns, int64_t t1_ns) = 0;
  // The device leaves (also when the client is destroyed).
  virtual void Leave(int device) = 0;
};

// `world` (not owned) in this process.
std::unique_ptr<WorldClient> LocalWorldClient(World* world);

// stage-sim's SimWorld at `address` (host:port). Fails if it does not answer within a few seconds.
absl::StatusOr<std::unique_ptr<WorldClient>> ConnectWorld(const std::string& address);

}  // namespace stage::sim
