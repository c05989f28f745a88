// The light node's judgement of the controller's heartbeat, over the time the node itself ran. The watchdog looks every
// tick; a gap between two looks far longer than a tick means the node did not run (its process was stopped, the
// machine starved it), and that time counts against nobody: the controller gets a full timeout from when the node
// runs again, since its heartbeats may be waiting to be read. Once per heartbeat: a second absence with no heartbeat
// in between counts, so a controller that is gone is found out within the timeout plus one absence of the node, even
// on a node that is starved again and again.
#pragma once

#include <algorithm>
#include <chrono>

namespace stage::light {

class HeartbeatWatch {
 public:
  using Clock = std::chrono::steady_clock;

  // A timeout of `timeout`, looked at every `tick()`.
  explicit HeartbeatWatch(std::chrono::milliseconds timeout = std::chrono::milliseconds(1000))
      : timeout_(timeout), tick_(std::max(std::chrono::milliseconds(10), timeout / 10)) {}

  // The watch starts (armed) or the controller's heartbeat came, at `now`.
  void Beat(Clock::time_point now) {
    last_beat_ = now;
    last_look_ = now;
    forgave_ = false;
  }
  // A look at `now`: true when the heartbeat has been missing for the timeout of the node's own running time.
  bool Expired(Clock::time_point now) {
    const auto gap = now - last_look_;
    if (gap > kAbsentTicks * tick_ && !forgave_) {
      last_beat_ += gap - tick_;  // the node was not running: not the controller's fault
      forgave_ = true;
    }
    last_look_ = now;
    return now - last_beat_ >= timeout_;
  }
  // When to look next.
  Clock::time_point NextLook(Clock::time_point now) const { return std::min(now + tick_, last_beat_ + timeout_); }
  std::chrono::milliseconds timeout() const { return timeout_; }
  std::chrono::milliseconds tick() const { return tick_; }

 private:
  // A gap of more than this many ticks between two looks is time the node did not run.
  static constexpr int kAbsentTicks = 3;
  std::chrono::milliseconds timeout_;
  std::chrono::milliseconds tick_;
  Clock::time_point last_beat_;
  Clock::time_point last_look_;
  bool forgave_ = false;  // an absence was forgiven since the last heartbeat
};

}  // namespace stage::light
