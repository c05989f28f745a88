// The sync generator: what produces the stage's slot clock, as the capture session drives it. A take is one or more
// runs of the clock (one more after each pause): the session plans a run (its first slot and the time of its first
// edge, T0, so that every camera knows T0 before the first edge), starts exactly the run it planned, may end it early
// at a frame boundary (pause, abort), and reads how far the clock has got.
//
// Slots are counted on the generator's own line (the bus): a take's slot 0 is the first slot of its first run.
// Implementations: a light node that drives the clock line (light_sync_generator.h), an external generator a light
// node timestamps (external_sync_generator.h), and the simulated world's bus (sim/, stage-sim's SimWorld service).
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace stage::controller {

struct SyncRunRequest {
  // Slots in the run. Above 0.
  int64_t slots = 0;
  // Start this many slots after the one passing now (time for every node to hear of the run's T0); a generator that
  // steps in lockstep with its devices starts right after its last run and ignores it.
  int64_t lead_slots = 0;
  // The run's first slot is a multiple of this (the pattern cycle, so that the take's cycles are the subject's
  // poses). At least 1.
  int64_t align_slots = 1;
  // Start no earlier than this slot (a take resumed after a pause: its gap lasts at least until then).
  int64_t min_first_slot = 0;
  // The take's first run (not a resume): where the lights start their tables (a clock that runs free).
  bool first_of_take = false;
};

// A run of the clock: slots [first_slot, end_slot) on the bus, its first edge at first_edge_ns on the stage's clock
// (the clock the cameras' T0 is in), and, read back, the slot whose edge the clock produced last (-1 before the
// run's first; the run is over once current_slot >= end_slot - 1).
struct SyncRun {
  int64_t first_slot = 0;
  int64_t end_slot = 0;
  int64_t first_edge_ns = 0;
  int64_t current_slot = -1;
};

class SyncGenerator {
 public:
  virtual ~SyncGenerator() = default;
  // In words, for messages: "the simulated world at 127.0.0.1:41234".
  virtual std::string Describe() const = 0;
  // The clock runs outside the take's runs too (an external generator): the light nodes arm to wait for the take's
  // first edge (LightNode.StartTable), not to start at the next one, and step through a pause's gap.
  virtual bool runs_free() const { return false; }
  // Which run a start would be, without starting it. Asked again while the generator is slow, up to `give_up`.
  virtual absl::StatusOr<SyncRun> Plan(const SyncRunRequest& request,
                                       std::chrono::steady_clock::time_point give_up) = 0;
  // Starts exactly the run `planned` (from Plan with the same request): the run as it started.
  virtual absl::StatusOr<SyncRun> Start(const SyncRunRequest& request, const SyncRun& planned,
                                        std::chrono::steady_clock::time_point give_up) = 0;
  // Ends the current run at the first slot after the one passing now that is a multiple of `align_slots` after the
  // run's first (1: the next slot): the run as it now is (its end_slot the new end). FailedPrecondition when there is
  // no run, or it is over.
  virtual absl::StatusOr<SyncRun> End(int64_t align_slots) = 0;
  // The last run as it now is. FailedPrecondition before the first run.
  virtual absl::StatusOr<SyncRun> GetRun() = 0;
};

// What the stage knows of a take beyond its frames: the simulator's ground truth (the scene behind every frame), for
// processing to be judged against. A real stage has none. Not a part of the control path: asked once a take's
// cameras are finished.
class TakeTruth {
 public:
  virtual ~TakeTruth() = default;
  // Writes the truth of bus frames [first_frame, first_frame + frames) into `dir` (docs/simulator.md#ground-truth),
  // the frame directories numbered from `name_offset`; `scene_only`: the true cameras and each frame's subject, not
  // every camera's per-pixel maps. Unimplemented where there is no truth to write.
  virtual absl::Status Write(const std::string& dir, int64_t name_offset, int64_t first_frame, int64_t frames,
                             bool scene_only) = 0;
};

}  // namespace stage::controller
