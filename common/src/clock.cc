// RealClock and SimClock.
#include "stage/common/clock.h"

#include <time.h>

#include <cerrno>

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

void RealClock::SleepUntilNs(int64_t t_ns) {
  timespec ts;
  ts.tv_sec = t_ns / kNsPerSec;
  ts.tv_nsec = t_ns % kNsPerSec;
  // Absolute sleeps do not accumulate drift; restart after signals.
  while (clock_nanosleep(ClockId(kind_), TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

int64_t SimClock::NowNs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return now_ns_;
}

void SimClock::SleepUntilNs(int64_t t_ns) {
  std::unique_lock<std::mutex> lock(mutex_);
  ++sleepers_;
  changed_.notify_all();  // a test may be waiting for sleepers() to change
  changed_.wait(lock, [&] { return now_ns_ >= t_ns; });
  --sleepers_;
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

}  // namespace stage
