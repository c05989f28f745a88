// Scheduled software triggers on the node.
#include "stage/timing/trigger_scheduler.h"

#include <pthread.h>
#include <sched.h>
#include <sys/prctl.h>
#include <time.h>

#include <chrono>
#include <cstring>

#include "stage/common/metrics.h"

namespace stage::timing {
namespace {

constexpr size_t kMaxListedSlots = 100;
constexpr size_t kDefaultLeadsKept = 100'000;

std::chrono::system_clock::time_point ToTimePoint(int64_t ns) {
  return std::chrono::system_clock::time_point(
      std::chrono::duration_cast<std::chrono::system_clock::duration>(std::chrono::nanoseconds(ns)));
}

}  // namespace

int64_t TriggerScheduler::NowNs() {
  timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

TriggerScheduler::TriggerScheduler(TriggerSchedulerOptions options, std::function<absl::Status(int64_t)> fire)
    : options_(options), fire_(std::move(fire)) {
  thread_ = std::thread([this] { Run(); });
}

TriggerScheduler::~TriggerScheduler() { Stop(); }

void TriggerScheduler::Submit(int64_t slot, int64_t due_ns) {
  const int64_t now = NowNs();
  std::lock_guard<std::mutex> lock(mutex_);
  ++stats_.received;
  if (options_.keep_all_leads || stats_.leads_ns.size() < kDefaultLeadsKept) stats_.leads_ns.push_back(due_ns - now);
  if (stopping_ || draining_ || now > due_ns + options_.max_late_ns) {
    ++stats_.missed;
    if (stats_.missed_slots.size() < kMaxListedSlots) stats_.missed_slots.push_back(slot);
    return;
  }
  queue_.push({due_ns, slot});
  ++generation_;
  changed_.notify_all();
}

void TriggerScheduler::CountLate(int64_t slot) {
  ++stats_.late;
  if (stats_.late_slots.size() < kMaxListedSlots) stats_.late_slots.push_back(slot);
}

void TriggerScheduler::Run() {
  prctl(PR_SET_TIMERSLACK, static_cast<unsigned long>(options_.timer_slack_ns));
  std::unique_lock<std::mutex> lock(mutex_);
  if (options_.realtime_priority > 0) {
    sched_param param{};
    param.sched_priority = options_.realtime_priority;
    if (int err = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param); err != 0) {
      stats_.warning = std::string("no SCHED_FIFO for the trigger thread (") + std::strerror(err) +
                       "): triggers fire with normal scheduling";
    }
  }
  while (true) {
    changed_.wait(lock, [&] { return stopping_ || draining_ || !queue_.empty(); });
    if (stopping_) break;
    if (queue_.empty()) {
      if (draining_) break;
      continue;
    }
    const Pending next = queue_.top();
    const uint64_t generation = generation_;
    // Sleep until just before it; an earlier trigger submitted meanwhile (generation changes) or Stop() wakes us.
    const int64_t wake = next.due_ns - options_.spin_ns;
    if (NowNs() < wake) {
      changed_.wait_until(lock, ToTimePoint(wake), [&] { return stopping_ || generation_ != generation; });
      if (stopping_) break;
      if (generation_ != generation && queue_.top().due_ns < next.due_ns) continue;
      if (NowNs() < wake) continue;  // woken early: sleep again
    }
    queue_.pop();
    lock.unlock();
    int64_t now = NowNs();
    while (now < next.due_ns) now = NowNs();
    absl::Status fired = absl::OkStatus();
    const bool in_time = now - next.due_ns <= options_.max_late_ns;
    if (in_time) fired = fire_(next.slot);
    lock.lock();
    if (in_time && fired.ok()) {
      ++stats_.fired;
      stats_.max_fire_late_ns = std::max(stats_.max_fire_late_ns, now - next.due_ns);
      if (options_.fire_lateness != nullptr)
        options_.fire_lateness->Observe(static_cast<double>(now - next.due_ns) * 1e-9);
    } else {
      CountLate(next.slot);
    }
  }
  // Whatever is left was never fired.
  while (!queue_.empty()) {
    ++stats_.missed;
    if (stats_.missed_slots.size() < kMaxListedSlots) stats_.missed_slots.push_back(queue_.top().slot);
    queue_.pop();
  }
}

void TriggerScheduler::Drain() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    draining_ = true;
  }
  changed_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void TriggerScheduler::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  changed_.notify_all();
  if (thread_.joinable()) thread_.join();
}

TriggerSchedulerStats TriggerScheduler::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

}  // namespace stage::timing
