// When a running take's frames are all in, judged from what its nodes report rather than from a clock of its own. A
// take waits for every device that is working, however slow the machine: a slot clock still producing the take's
// edges, a camera that owes frames it was triggered for and is working on (a simulated camera renders them, a real one
// reads them out). It ends early only when nothing more can come: the clock has produced every edge and no camera owes
// a frame (the missing frames are lost, and the ledger says why), or nothing at all has moved for the stall limit
// (a device hung while it still answers).
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace stage::controller {

// One poll of a running take's nodes.
struct TakeSnapshot {
  struct Camera {
    std::string id;
    // Its node answered this poll. A node that did not keeps the values of its last answer.
    bool answered = false;
    // The node is gone (its process is not there): it owes nothing any longer.
    bool down = false;
    int64_t expected = 0;  // frames the take expects of it so far (pauses excluded)
    int64_t received = 0;
    // Frames it was triggered for and has not delivered yet, and a counter that grows while its device works on them.
    int64_t owed = 0;
    uint64_t work = 0;
    // What the device is doing, in words ("precomputing the subject's pose of frame 0: 45 %").
    std::string activity;
  };
  std::vector<Camera> cameras;
  // The slot clock's current run: edges produced so far and in all; unset where the generator did not answer.
  std::optional<int64_t> clock_edges;
  int64_t clock_run_slots = 0;
};

enum class TakeVerdict {
  kComplete,  // every expected frame is in
  kUnderWay,  // frames are still coming, or a device is still working on them
  kDrained,   // the clock has produced every edge, no camera owes a frame, and the drain has passed
  kStalled,   // nothing moved for the stall limit while the take was not complete
};

struct TakeWatchOptions {
  // Once the clock has ended and no camera owes a frame, frames still in transit may take this long.
  std::chrono::milliseconds drain{3000};
  // No progress at all (no frame, no device work, no clock edge) for this long: the take is stalled. 0: never.
  std::chrono::milliseconds stall{std::chrono::seconds(120)};
};

class TakeWatch {
 public:
  using TimePoint = std::chrono::steady_clock::time_point;

  TakeWatch(TakeWatchOptions options, TimePoint start);

  // Judges one poll, made at `now`.
  TakeVerdict Observe(const TakeSnapshot& snapshot, TimePoint now);
  // The take's plan changed, or it is paused: whatever it waits for starts again from `now`.
  void Restart(TimePoint now);

  // What the take waits for, in words, after the last Observe ("hs-1 owes 2 frames (rendering slot 12); the slot
  // clock: 30 of 38 edges"); empty when nothing.
  const std::string& waiting_for() const { return waiting_for_; }
  // Frames owed by the cameras in the last snapshot (their last answers).
  int64_t owed() const { return owed_; }
  // Since when nothing has moved.
  TimePoint quiet_since() const { return quiet_since_; }

 private:
  struct Known {
    int64_t received = 0;
    int64_t owed = 0;
    uint64_t work = 0;
    bool down = false;
    std::string activity;
  };
  // Folds the snapshot into what is known; true if anything moved.
  bool Fold(const TakeSnapshot& snapshot);
  void Describe(const TakeSnapshot& snapshot);

  TakeWatchOptions options_;
  TimePoint quiet_since_;
  std::map<std::string, Known> cameras_;
  std::optional<int64_t> clock_edges_;
  int64_t clock_run_slots_ = 0;
  int64_t owed_ = 0;
  std::string waiting_for_;
};

}  // namespace stage::controller
