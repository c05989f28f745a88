// The simulated world: the time base, the trigger bus (slot edges) and what the LEDs emitted. It is a broker of
// state, not a renderer: light drivers tell it what their channels did, cameras ask it what light fell during their
// exposures and render in their own processes.
//
// Two modes:
//  - lockstep: time stands at slot k's edge until every registered device has said it is done with slot k (by
//    waiting for a later edge, or finishing); then it moves to slot k+1. Deterministic whatever the machine's load,
//    for tests.
//  - real time: edges come with the host clock (a SlotClock); a device that waits for an edge that has already
//    passed learns how many it missed, as hardware would.
//
// Emission is complete up to a light node's *watermark*: the node promises no change before it (its next switch).
// An exposure query waits until every light node's watermark has passed the exposure's end, so a camera renders only
// what the LEDs actually did; a light node that leaves (stopped, crashed) goes dark from its last watermark on and
// no longer holds anyone up.
#pragma once

#include <climits>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/sim/dome.h"
#include "stage/sim/emission.h"
#include "stage/timing/slot_clock.h"
#include "stage/timing/time_base.h"
#include "stage/v1/rig.pb.h"

namespace stage::sim {

struct WorldOptions {
  uint32_t slot_rate_hz = 912;
  bool lockstep = true;
  // Real time: host clock (CLOCK_MONOTONIC) time of slot 0, ns; 0 picks 100 ms after Start(). Lockstep time starts at
  // 0 = slot 0.
  int64_t t0_ns = 0;
  // Rise and fall time of each light node's emitters (its slowest), ns, by node index.
  std::vector<int64_t> rise_ns, fall_ns;
  // How much emission the world keeps behind the slowest light node's watermark, ns: an exposure that ends earlier
  // than that cannot be rendered (the camera fell too far behind) and is refused. Default 2 s.
  int64_t history_ns = 2'000'000'000;
  // The world ends after this many slots (a take's length): no edge at or after it is delivered. -1: runs on.
  int64_t end_slot = -1;
  // The bus carries edges only in runs, as a sync generator drives its lines only during a take. true: one run from
  // slot 0 on, from Start() (until end_slot); false: none until Run() asks for one (the controller's takes).
  bool open_run = true;
  // Tests only: called on the real-time clock's thread before the world takes each edge. A hook that sleeps makes the
  // clock late, as a loaded machine does, so that it skips slots. Empty: none.
  std::function<void(int64_t slot)> before_real_edge;
};

// A run of the bus: edges in slots [first, end).
struct WorldRun {
  int64_t first = 0;
  int64_t end = INT64_MAX;
  // The device whose line carries the run (a sync generator light node's id), or empty (the world drives it): when
  // that device leaves the world, the run ends at the next slot.
  std::string driver;
};

struct WorldEdge {
  int64_t slot = 0;
  // The edge's time on the world's clock, ns (lockstep: ns since slot 0).
  int64_t time_ns = 0;
  // Edges that passed since the device's previous wait without it (real time only).
  int64_t missed = 0;
  // Faults injected at run time for this device since its previous edge (InjectFault), oldest first.
  std::vector<v1::SimFault> faults;
  // The run the edge belongs to: divided lines (a camera's every-38th trigger) count from its first slot.
  WorldRun run;
};

class World {
 public:
  World(const Dome& dome, WorldOptions options);
  ~World();

  // Starts the clock (real time) or opens slot 0 (lockstep).
  void Start();
  // Wakes every waiter; no edge is delivered after this.
  void Stop();

  // A device that takes part in lockstep. Light nodes give their node index (their emission is theirs), cameras -1.
  int Register(const std::string& name, int light_node = -1);
  // The device is gone: it holds nobody up any longer; a light node goes dark from its watermark on; a run it drives
  // ends at the next slot.
  void Unregister(int device);

  // Blocks until slot `slot`'s edge (which also says the device is done with every earlier slot). nullopt after
  // Stop() or once the device is unregistered.
  std::optional<WorldEdge> WaitForEdge(int device, int64_t slot);
  // The device is done with `slot` and will not wait for more (lockstep: lets time move on).
  void Done(int device, int64_t slot);

  // A light node's channels change to `levels` at `t_ns`; it promises no other change before `watermark_ns`.
  void ReportLevels(int light_node, int64_t t_ns, const std::vector<double>& levels, int64_t watermark_ns);
  void ReportWatermark(int light_node, int64_t watermark_ns);

  // Every unit's emitters averaged over [t0, t1]; waits until every registered light node has reported past t1, or
  // (real time) until the bus has been silent through t1 since a run every node has answered to its end.
  // Cancelled after Stop(); OutOfRange when the window is older than the history the world keeps.
  absl::StatusOr<EmitterLevels> Exposure(int64_t t0_ns, int64_t t1_ns);

  // LED unit `unit` (dome index) fails as `fault` says from now on.
  void SetUnitFault(size_t unit, UnitFault fault) { emission_.SetUnitFault(unit, fault); }
  // A fault at run time (the fields of sim.faults; checked by the caller): an LED unit's state (dead, delay) changes
  // now; a light node or camera (every device registered under that name) gets it with its next edge and applies
  // the fields it sets. NotFound when the target is neither a unit of the dome nor a device in the world.
  absl::Status InjectFault(const v1::SimFault& fault);

  // A run of `count` slots (a take): lockstep, right after the last run (or at slot 0); real time, `lead_slots` after
  // the slot passing now (and after the last run); its first slot a multiple of `align` (the pattern cycle, so that
  // a take's cycles are the subject's poses). FailedPrecondition while the last run is still open-ended.
  // `min_first`: the run starts no earlier than this slot (a take resumed after a pause).
  absl::StatusOr<WorldRun> Run(int64_t count, int64_t lead_slots = 0, int64_t align = 1, int64_t min_first = 0);
  // The run Run() would make now, without making it (the controller arms every node for it first), and that run made
  // (FailedPrecondition if it no longer fits: it overlaps the last run, or real time has passed its first slot).
  absl::StatusOr<WorldRun> PlanRun(int64_t count, int64_t lead_slots = 0, int64_t align = 1,
                                   int64_t min_first = 0) const;
  // Starting the run that was started last is a no-op (idempotent: a retried request).
  absl::Status StartRun(const WorldRun& run);
  // Ends the last run early (a take paused or aborted): at the first slot after the edge the world stands at (or
  // last passed) that is a multiple of `align` after the run's first, if that is sooner than its end. Returns the run
  // as it now is; FailedPrecondition when there is no run, it is open-ended, or it is over.
  absl::StatusOr<WorldRun> EndRun(int64_t align = 1);

  // The edge the world stands at (lockstep) or last passed (real time).
  int64_t current_slot() const;
  // The last run as it now is (an EndRun shortens it); nullopt before the first.
  std::optional<WorldRun> LastRun() const;
  const timing::TimeBase& base() const { return base_; }
  int64_t EdgeNs(int64_t slot) const { return options_.t0_ns + base_.SlotStartNs(slot); }

 private:
  struct Device {
    std::string name;
    int light_node = -1;
    // Lockstep: the last slot the device is done with.
    int64_t done_through = -1;
    // Real time: the last edge delivered to it.
    int64_t last_seen = -1;
    bool active = true;
    std::vector<v1::SimFault> faults;  // injected, not yet delivered
  };
  void MaybeAdvance();  // mutex_ held
  void OnRealEdge(const timing::SlotEdge& edge);
  void OnRealEnd();  // the clock passed end_slot
  // Every run slot before `slot` has passed (the clock skipped the last of them): the world stands at least at the
  // last one (mutex_ held).
  void PassRunSlotsBefore(int64_t slot);
  // The first slot at or after `slot` that lies in a run, or -1 (mutex_ held); the run of an in-run slot.
  int64_t NextEdge(int64_t slot) const;
  WorldRun RunOf(int64_t slot) const;
  // Edges (in-run slots) in [from, to).
  int64_t EdgesBetween(int64_t from, int64_t to) const;

  const Dome& dome_;
  WorldOptions options_;
  timing::TimeBase base_;
  EmissionState emission_;
  std::unique_ptr<timing::SlotClock> clock_;
  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<Device> devices_;        // guarded by mutex_
  std::map<int, int64_t> watermarks_;  // light node -> ns; guarded by mutex_
  int64_t current_ = -1;               // guarded by mutex_
  // Real time, between runs: the bus has been silent from the last run's end (quiet_from_ns_, the edge time of its
  // end slot) through quiet_through_ns_ (the last silent edge). A light node that has answered the run's last edge
  // (its watermark reaches quiet_from_ns_) changes no level until the next run, which starts ahead of now: its light
  // is known through quiet_through_ns_. INT64_MIN until a silent slot after a run passes.
  int64_t quiet_from_ns_ = INT64_MIN;       // guarded by mutex_
  int64_t quiet_through_ns_ = INT64_MIN;    // guarded by mutex_
  std::vector<WorldRun> runs_;              // in order, disjoint; guarded by mutex_
  int64_t forgotten_before_ = INT64_MIN;    // guarded by mutex_
  bool started_ = false, stopped_ = false;  // guarded by mutex_
};

}  // namespace stage::sim
