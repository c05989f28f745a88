// RealClock and SimClock.
#include "stage/common/clock.h"

#include <time.h>

#include <chrono>

namespace stage {
namespace {

constexpr int64_t kNsPerSec = 1'000'000'000;

clockid_t ClockId(RealClock::Kind kind) {
  return kind == RealClock::Kind::kMonotonic ? CLOCK_MONOTONIC : CLOCK_REALTIME;
}

}  // namespace

int64_t RealClock::NowNs() const {
  timespec ts;
  clock_gettime(ClockId(kind_), &ts);
  return static_cast<int64_t>(ts.tv_sec) * kNsPerSec + ts.tv_nsec;
}

bool RealClock::SleepUntilNs(int64_t t_ns, const std::atomic<bool>& stop) {
  std::unique_lock<std::mutex> lock(mutex_);
  // Absolute deadlines on the same clock, so sleeps do not accumulate drift. libstdc++ waits on CLOCK_MONOTONIC for
  // steady_clock and CLOCK_REALTIME for system_clock, the clocks NowNs() reads.
  while (true) {
    if (stop.load()) return false;
    if (NowNs() >= t_ns) return true;
    if (kind_ == Kind::kMonotonic) {
      wake_.wait_until(lock, std::chrono::steady_clock::time_point(std::chrono::nanoseconds(t_ns)));
    } else {
      wake_.wait_until(
          lock, std::chrono::system_clock::time_point(
                    std::chrono::duration_cast<std::chrono::system_clock::duration>(std::chrono::nanoseconds(t_ns))));
    }
  }
}

void RealClock::Interrupt() {
  // Taking the lock orders this wake-up after any sleeper's read of its flag: it is either before the sleeper's
  // check (which then sees the flag) or while the sleeper waits (which this notify ends).
  { std::lock_guard<std::mutex> lock(mutex_); }
  wake_.notify_all();
}

int64_t SimClock::NowNs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return now_ns_;
}

bool SimClock::SleepUntilNs(int64_t t_ns, const std::atomic<bool>& stop) {
  std::unique_lock<std::mutex> lock(mutex_);
  ++sleepers_;
  changed_.wait(lock, [&] { return now_ns_ >= t_ns || stop.load(); });
  --sleepers_;
  return !stop.load();
}

void SimClock::Interrupt() {
  { std::lock_guard<std::mutex> lock(mutex_); }  // see RealClock::Interrupt
  changed_.notify_all();
}

void SimClock::AdvanceTo(int64_t t_ns) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (t_ns <= now_ns_) return;
    now_ns_ = t_ns;
  }
  changed_.notify_all();
}

void SimClock::Advance(int64_t delta_ns) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (delta_ns <= 0) return;
    now_ns_ += delta_ns;
  }
  changed_.notify_all();
}

int SimClock::sleepers() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return sleepers_;
}

int64_t UnixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace stage
