// The slot clock a light node drives when it is the rig's sync generator (timing.sync_generator): runs of edges on its
// clock line, planned and started by the controller (LightNode.RunSlotClock in light_node.proto). Implementations: the
// gpiod backend's clock output, and in simulation the world's bus (sim/: the node's clock line is a wire of the
// simulated world, which every camera and board sees).
#pragma once

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"
#include "stage/v1/light_node.pb.h"

namespace stage::light {

class SlotClockGenerator {
 public:
  virtual ~SlotClockGenerator() = default;
  // In words, for messages: "the simulated world's bus at 127.0.0.1:40001".
  virtual std::string Describe() const = 0;
  // Plans a run (plan_only), or starts exactly the planned one (first_slot), or plans and starts; see
  // SlotClockRunRequest. Starting the run it started last again is a no-op.
  virtual absl::StatusOr<v1::SlotClockRun> Run(const v1::SlotClockRunRequest& request) = 0;
  // Ends the current run at the next multiple of `align_slots` after its first; FailedPrecondition with no run, or
  // one that is over.
  virtual absl::StatusOr<v1::SlotClockRun> End(int64_t align_slots) = 0;
  // The last run as it now is; FailedPrecondition before the first.
  virtual absl::StatusOr<v1::SlotClockRun> Get() = 0;
};

}  // namespace stage::light
