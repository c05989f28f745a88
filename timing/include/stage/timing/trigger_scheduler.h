// Fires scheduled software triggers at absolute times on the node's clock (CLOCK_REALTIME, PTP-disciplined in
// production). Triggers arrive ahead of time (the controller streams them timing.trigger_lead_slots early); each
// fires at its time on one thread with reduced timer slack and an optional spin. Nothing is merged or fired blind:
//  - a trigger that arrives more than max_late after its time is missed (never fired);
//  - a trigger the thread cannot fire within max_late of its time is late (not fired: its exposure would leave
//    the slot's steady light);
// both are counted with their slots, and every trigger's lead (its time minus its arrival) is kept for reports.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <queue>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"

namespace stage::metrics {
class Histogram;
}  // namespace stage::metrics

namespace stage::timing {

struct TriggerSchedulerOptions {
  // How late a trigger may still fire, ns (the schedule's late slack).
  int64_t max_late_ns = 100'000;
  // Timer slack of the firing thread, ns.
  int64_t timer_slack_ns = 1;
  // Wake this long before each trigger and spin until it, ns.
  int64_t spin_ns = 0;
  // Keep every lead (for benchmarks); otherwise the first 100000.
  bool keep_all_leads = false;
  // SCHED_FIFO priority of the firing thread, 1..99; 0 = normal scheduling. Without CAP_SYS_NICE the thread runs
  // normally and `stats().warning` says so.
  int realtime_priority = 0;
  // Where each fired trigger's lateness (fire time minus due time, seconds) is observed; nullptr: nowhere.
  metrics::Histogram* fire_lateness = nullptr;
};

struct TriggerSchedulerStats {
  uint64_t received = 0;
  uint64_t fired = 0;
  uint64_t late = 0;
  uint64_t missed = 0;
  // The first 100 of each.
  std::vector<int64_t> late_slots;
  std::vector<int64_t> missed_slots;
  // Leads in arrival order, ns.
  std::vector<int64_t> leads_ns;
  int64_t max_fire_late_ns = 0;
  // Set when the firing thread could not get the real-time priority it was asked for.
  std::string warning;
};

class TriggerScheduler {
 public:
  // `fire` is called on the scheduler's thread at each trigger's time with its slot; an error counts the trigger
  // late. Starts the thread.
  TriggerScheduler(TriggerSchedulerOptions options, std::function<absl::Status(int64_t slot)> fire);
  // Stop().
  ~TriggerScheduler();

  // A trigger for `slot` due at `due_ns` on CLOCK_REALTIME, arriving now. Thread-safe.
  void Submit(int64_t slot, int64_t due_ns);

  // Returns once every submitted trigger has fired or been counted; the scheduler then stops.
  void Drain();
  // Stops now; triggers not yet due are counted missed.
  void Stop();

  TriggerSchedulerStats stats() const;

  // CLOCK_REALTIME, ns.
  static int64_t NowNs();

 private:
  struct Pending {
    int64_t due_ns;
    int64_t slot;
    bool operator>(const Pending& o) const { return due_ns != o.due_ns ? due_ns > o.due_ns : slot > o.slot; }
  };
  void Run();
  void CountLate(int64_t slot);  // mutex_ held

  TriggerSchedulerOptions options_;
  std::function<absl::Status(int64_t)> fire_;
  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::priority_queue<Pending, std::vector<Pending>, std::greater<Pending>> queue_;  // guarded by mutex_
  uint64_t generation_ = 0;                                                          // guarded by mutex_
  bool draining_ = false;                                                            // guarded by mutex_
  bool stopping_ = false;                                                            // guarded by mutex_
  TriggerSchedulerStats stats_;                                                      // guarded by mutex_
  std::thread thread_;
};

}  // namespace stage::timing
