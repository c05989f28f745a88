// The slot-clock generator.
#include "stage/timing/slot_clock.h"

#include <pthread.h>
#include <sched.h>
#include <sys/prctl.h>
#include <time.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <future>

#include "absl/strings/str_cat.h"
#include "stage/common/status.h"

namespace stage::timing {
namespace {

constexpr int64_t kNsPerSecond = 1'000'000'000;
// Longest single sleep, so that Stop() is noticed soon even at low slot rates.
constexpr int64_t kMaxSleepNs = 20'000'000;

timespec ToTimespec(int64_t ns) {
  timespec ts;
  ts.tv_sec = ns / kNsPerSecond;
  ts.tv_nsec = ns % kNsPerSecond;
  return ts;
}

}  // namespace

int64_t HostClockNs(bool realtime_clock) {
  timespec ts;
  clock_gettime(realtime_clock ? CLOCK_REALTIME : CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * kNsPerSecond + ts.tv_nsec;
}

void SleepUntilHostNs(int64_t ns, bool realtime_clock) {
  if (ns <= 0) return;
  const timespec ts = ToTimespec(ns);
  while (clock_nanosleep(realtime_clock ? CLOCK_REALTIME : CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

absl::Status SlotClockOptions::Validate() const {
  if (slot_rate_hz < 1 || slot_rate_hz > 1'000'000) {
    return absl::InvalidArgumentError(absl::StrCat("slot_rate_hz ", slot_rate_hz, " is not in [1, 1000000]"));
  }
  if (first_slot < 0) return absl::InvalidArgumentError(absl::StrCat("first_slot ", first_slot, " is negative"));
  if (timer_slack_ns < 1) {
    return absl::InvalidArgumentError(absl::StrCat("timer_slack_ns ", timer_slack_ns, " is not >= 1"));
  }
  if (spin_ns < 0 || spin_ns >= kNsPerSecond / slot_rate_hz) {
    return absl::InvalidArgumentError(absl::StrCat("spin_ns ", spin_ns, " is not in [0, one slot)"));
  }
  if (realtime_priority < 0 || realtime_priority > 99) {
    return absl::InvalidArgumentError(absl::StrCat("realtime_priority ", realtime_priority, " is not in [0, 99]"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<SlotClock>> SlotClock::Create(const SlotClockOptions& options, Clock* clock) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(TimeBase base, TimeBase::Create(options.slot_rate_hz));
  return std::unique_ptr<SlotClock>(new SlotClock(options, base, clock));
}

SlotClock::SlotClock(SlotClockOptions options, TimeBase base, Clock* clock)
    : options_(options), base_(base), clock_(clock) {}

SlotClock::~SlotClock() { Stop(); }

void SlotClock::AddListener(SlotListener listener) { listeners_.push_back(std::move(listener)); }

void SlotClock::AddEndListener(SlotRunEndListener listener) { end_listeners_.push_back(std::move(listener)); }

absl::Status SlotClock::Start() {
  if (thread_.joinable()) return absl::FailedPreconditionError("the slot clock is already started");
  if (clock_ != nullptr) {
    thread_ = std::thread([this] { RunVirtual(); });
    return absl::OkStatus();
  }
  std::promise<absl::Status> ready;
  std::future<absl::Status> started = ready.get_future();
  thread_ = std::thread([this, &ready] {
    // The wake-up precision of this thread: timer slack (default 50 us) and, if asked, real-time scheduling.
    prctl(PR_SET_TIMERSLACK, static_cast<unsigned long>(options_.timer_slack_ns));
    if (options_.realtime_priority > 0) {
      sched_param param{};
      param.sched_priority = options_.realtime_priority;
      if (int err = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param); err != 0) {
        ready.set_value(absl::PermissionDeniedError(
            absl::StrCat("slot clock: cannot run at SCHED_FIFO priority ", options_.realtime_priority, ": ",
                         std::strerror(err), " (needs CAP_SYS_NICE; set realtime_priority 0 to run without)")));
        return;
      }
    }
    ready.set_value(absl::OkStatus());
    RunRealTime();
  });
  absl::Status status = started.get();
  if (!status.ok()) thread_.join();
  return status;
}

void SlotClock::Stop() {
  stop_.store(true);
  // The virtual-mode thread sleeps on the clock with stop_ (a clock never started is not touched: it may be gone).
  if (clock_ != nullptr && thread_.joinable()) clock_->Interrupt();
  if (thread_.joinable()) thread_.join();
}

void SlotClock::Wait() {
  if (thread_.joinable()) thread_.join();
}

SlotClockStats SlotClock::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

void SlotClock::Deliver(const SlotEdge& edge) {
  for (const SlotListener& listener : listeners_) listener(edge);
  std::lock_guard<std::mutex> lock(mutex_);
  ++stats_.edges;
  stats_.missed += static_cast<uint64_t>(edge.missed_before);
  stats_.max_late_ns = std::max(stats_.max_late_ns, edge.actual_ns - edge.scheduled_ns);
}

void SlotClock::DeliverEnd(int64_t missed_at_end) {
  for (const SlotRunEndListener& listener : end_listeners_) listener(missed_at_end);
}

void SlotClock::RunVirtual() {
  const int64_t end = options_.slot_count < 0 ? INT64_MAX : options_.first_slot + options_.slot_count;
  for (int64_t k = options_.first_slot; k < end && !stop_.load(); ++k) {
    const int64_t due = EdgeNs(k);
    if (!clock_->SleepUntilNs(due, stop_)) return;
    Deliver({k, due, clock_->NowNs(), 0});
  }
  if (!stop_.load() && options_.slot_count >= 0) DeliverEnd(0);
}

void SlotClock::RunRealTime() {
  const int64_t end = options_.slot_count < 0 ? INT64_MAX : options_.first_slot + options_.slot_count;
  const int64_t period = kNsPerSecond / options_.slot_rate_hz;  // for the "a slot late" test only
  int64_t k = options_.first_slot;
  int64_t missed = 0;
  while (k < end && !stop_.load()) {
    const int64_t due = EdgeNs(k);
    const int64_t wake = due - options_.spin_ns;
    // Sleep in bounded steps so that Stop() is seen; the last step ends at `wake` exactly.
    for (int64_t now = HostClockNs(options_.realtime_clock); now < wake && !stop_.load();
         now = HostClockNs(options_.realtime_clock)) {
      SleepUntilHostNs(std::min(wake, now + kMaxSleepNs), options_.realtime_clock);
    }
    if (stop_.load()) break;  // edges skipped so far are still counted below
    int64_t now = HostClockNs(options_.realtime_clock);
    while (now < due) now = HostClockNs(options_.realtime_clock);
    if (now - due >= period) {
      // A slot or more late: those edges have passed. Go on with the slot that is current now.
      const int64_t current = base_.SlotAtNs(now - options_.t0_ns);
      const int64_t skip = std::min(current, end) - k;
      missed += skip;
      k += skip;
      if (k >= end) break;
      continue;
    }
    Deliver({k, due, now, missed});
    missed = 0;
    ++k;
  }
  if (missed > 0) {
    std::lock_guard<std::mutex> lock(mutex_);
    stats_.missed += static_cast<uint64_t>(missed);
  }
  if (!stop_.load() && k >= end) DeliverEnd(missed);
}

}  // namespace stage::timing
