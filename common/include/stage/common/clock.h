// Time sources. Code that waits or timestamps takes a Clock so tests can run it in virtual time (SimClock) and
// production runs it on the host clock (RealClock). Times are int64 nanoseconds on the clock's own epoch.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <mutex>

namespace stage {

class Clock {
 public:
  virtual ~Clock() = default;
  // Current time, ns. Monotonic: never goes backwards. Thread-safe.
  virtual int64_t NowNs() const = 0;
  // Blocks the calling thread until NowNs() >= t_ns (returns true) or until `stop` is set (returns false). Returns
  // at once if that time has passed or `stop` is already set. `stop` is read under the clock's own lock, so a thread
  // that sets it and then calls Interrupt() always wakes the sleeper, however the two race (no lost wake-up).
  virtual bool SleepUntilNs(int64_t t_ns, const std::atomic<bool>& stop) = 0;
  // Wakes every sleeper so that it re-reads its `stop` flag; sleepers whose flag is clear sleep on.
  virtual void Interrupt() = 0;
};

// The host's clock. `kMonotonic` (CLOCK_MONOTONIC) for intervals and deadlines, `kRealtime` (CLOCK_REALTIME,
// disciplined by PTP in production) for timestamps shared between hosts.
class RealClock final : public Clock {
 public:
  enum class Kind { kMonotonic, kRealtime };
  explicit RealClock(Kind kind = Kind::kMonotonic) : kind_(kind) {}
  int64_t NowNs() const override;
  bool SleepUntilNs(int64_t t_ns, const std::atomic<bool>& stop) override;
  void Interrupt() override;

 private:
  Kind kind_;
  std::mutex mutex_;
  std::condition_variable wake_;
};

// A virtual clock that moves only when told to. Sleepers wake when the time they wait for is reached.
class SimClock final : public Clock {
 public:
  explicit SimClock(int64_t start_ns = 0) : now_ns_(start_ns) {}
  int64_t NowNs() const override;
  bool SleepUntilNs(int64_t t_ns, const std::atomic<bool>& stop) override;
  void Interrupt() override;
  // Moves time forward to `t_ns` (ignored if that is in the past) and wakes the sleepers it releases.
  void AdvanceTo(int64_t t_ns);
  void Advance(int64_t delta_ns);
  // Number of threads blocked in SleepUntilNs now; lets a test wait until a worker is parked.
  int sleepers() const;

 private:
  mutable std::mutex mutex_;
  std::condition_variable changed_;
  int64_t now_ns_;           // guarded by mutex_
  int sleepers_ = 0;         // guarded by mutex_
};

// Wall-clock time now (std::chrono::system_clock), Unix ns: the timestamps of statuses, records and logs.
int64_t UnixNowNs();

}  // namespace stage
