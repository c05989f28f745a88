// An external sync generator (a signal generator, or a camera's timer output, that the operator starts and that runs
// free) as the controller's sync generator. The controller cannot start or stop it; it watches it through a light node
// whose slot-clock input timestamps its edges (the rig's timing.clock_witness):
//  - Plan: the clock must be running; the take's first slot is `lead_slots` after the last edge the witness saw,
//    aligned to the pattern cycle on the line's numbering, and its T0 predicted from that edge and the rig's rate;
//  - Start: every light node has been told that edge (LightNode.StartTable; runs_free()); the run starts when the
//    witness's table starts, and T0 is the time the witness measured for that edge (the cameras hear it again when it
//    differs from the prediction);
//  - End (a pause, an abort): the run ends at a frame boundary `end_margin_slots` after the last edge seen (time for
//    every camera to hear of it); the clock itself goes on, and the lights keep stepping through the gap;
//  - GetRun: how far the witness has seen the line; a line gone quiet before the run's end is a lost generator.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/v1/light_node.pb.h"
#include "stage/v1/rig.pb.h"
#include "sync_generator.h"

namespace stage::controller {

// The light node that timestamps the external clock's edges (LightNode.GetClockInput).
class ClockWitness {
 public:
  virtual ~ClockWitness() = default;
  // In words, for messages: "light node lights-gpio-2 at 127.0.0.1:40012".
  virtual std::string Describe() const = 0;
  virtual absl::StatusOr<v1::ClockInput> Read() = 0;
};

std::unique_ptr<ClockWitness> NewGrpcClockWitness(const v1::LightNodeConfig& node);

struct ExternalGeneratorOptions {
  // The rig's slot rate, Hz (the generator's nominal rate: a T0 is predicted from the last edge with it). Above 0.
  double slot_rate_hz = 912;
  // A pause or abort ends the run at the first frame boundary at least this many slots after the last edge the witness
  // saw (the cameras hear of the new end before it comes). At least 1. Default 92 (0.1 s at 912 Hz).
  int64_t end_margin_slots = 92;
  // How often the witness is read while waiting for an edge. Above 0. Default 10 ms.
  std::chrono::milliseconds poll{10};

  absl::Status Validate() const;
};

absl::StatusOr<std::unique_ptr<SyncGenerator>> NewExternalSyncGenerator(std::unique_ptr<ClockWitness> witness,
                                                                        ExternalGeneratorOptions options);

}  // namespace stage::controller
