// The slot-clock generator: calls its listeners at every slot edge of a take, edge k at t0 + k / slot_rate exactly
// (each edge rounded to the nanosecond on its own, so nothing drifts). A gpiod light node that is the sync generator
// drives the slot-clock line on it (light-node/src/gpiod_light_driver.cc).
//
// Two modes:
//  - virtual: on a Clock such as SimClock. Every edge is delivered, in order, when the clock reaches it;
//    deterministic, for tests and the lockstep simulator.
//  - real time: on the host clock (CLOCK_MONOTONIC or CLOCK_REALTIME) with absolute clock_nanosleep sleeps, the
//    thread's timer slack reduced, optionally a short spin before each edge and SCHED_FIFO. An edge the thread reaches
//    a whole slot late or more is missed, counted, and never delivered late: like a hardware line, the generator
//    goes on with the current slot.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/clock.h"
#include "stage/timing/time_base.h"

namespace stage::timing {

struct SlotEdge {
  int64_t slot = 0;
  // When the edge was due and when the listener was called, ns on the generator's clock.
  int64_t scheduled_ns = 0;
  int64_t actual_ns = 0;
  // Edges skipped just before this one because the generator was a slot or more late.
  int64_t missed_before = 0;
};

// Called on the generator's thread at each edge; must return quickly (well within a slot).
using SlotListener = std::function<void(const SlotEdge&)>;
// Called on the generator's thread once, when a run of slot_count slots is over (never after Stop()), with the
// run's last slots the generator skipped after its last edge because it was a slot or more late (0 when none): no
// edge comes after them to carry them as missed_before.
using SlotRunEndListener = std::function<void(int64_t missed_at_end)>;

struct SlotClockOptions {
  // Slots per second. Required (1..1000000).
  uint32_t slot_rate_hz = 912;
  // Time of slot 0 on the generator's clock, ns.
  int64_t t0_ns = 0;
  // First slot to deliver, and how many; slot_count < 0 runs until Stop().
  int64_t first_slot = 0;
  int64_t slot_count = -1;

  // Real time only. Which host clock: CLOCK_MONOTONIC (default) or CLOCK_REALTIME (PTP-disciplined, shared
  // between hosts).
  bool realtime_clock = false;
  // Timer slack of the generator thread, ns. Linux adds up to 50 us to every timed wake-up by default.
  int64_t timer_slack_ns = 1;
  // Wake this long before each edge and spin until it (0 = sleep to the edge).
  int64_t spin_ns = 0;
  // SCHED_FIFO priority of the generator thread, 1..99; 0 = normal scheduling. Needs CAP_SYS_NICE; Start() fails
  // with a message if it cannot be set.
  int realtime_priority = 0;

  absl::Status Validate() const;
};

struct SlotClockStats {
  uint64_t edges = 0;
  uint64_t missed = 0;
  int64_t max_late_ns = 0;
};

class SlotClock {
 public:
  // Real time on the host clock when `clock` is null; virtual on `clock` (not owned, outlives the generator)
  // otherwise.
  static absl::StatusOr<std::unique_ptr<SlotClock>> Create(const SlotClockOptions& options, Clock* clock = nullptr);
  // Stops.
  ~SlotClock();

  // Before Start().
  void AddListener(SlotListener listener);
  void AddEndListener(SlotRunEndListener listener);

  // Starts the generator thread. Once.
  absl::Status Start();
  // Stops after the edge in progress; idempotent. No listener is called after it returns.
  void Stop();
  // Blocks until the last slot was delivered (slot_count >= 0) or Stop().
  void Wait();

  SlotClockStats stats() const;
  const TimeBase& base() const { return base_; }

 private:
  SlotClock(SlotClockOptions options, TimeBase base, Clock* clock);
  void RunVirtual();
  void RunRealTime();
  void Deliver(const SlotEdge& edge);
  void DeliverEnd(int64_t missed_at_end);
  int64_t EdgeNs(int64_t slot) const { return options_.t0_ns + base_.SlotStartNs(slot); }

  SlotClockOptions options_;
  TimeBase base_;
  Clock* clock_;
  std::vector<SlotListener> listeners_;
  std::vector<SlotRunEndListener> end_listeners_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  absl::Status start_status_;          // the thread's setup result (real-time priority)
  mutable std::mutex mutex_;
  SlotClockStats stats_;  // guarded by mutex_
};

// Nanoseconds on CLOCK_MONOTONIC or CLOCK_REALTIME.
int64_t HostClockNs(bool realtime_clock);
// Sleeps until `ns` on that clock (absolute clock_nanosleep, resumed after a signal); returns at once for a time past
// or <= 0.
void SleepUntilHostNs(int64_t ns, bool realtime_clock);

}  // namespace stage::timing
