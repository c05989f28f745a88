// The events of the session's current take: see take_events.h.
#include "take_events.h"

#include <vector>

namespace stage::controller {

TakeEvents::Joined TakeEvents::Subscribe(CaptureEventFn fn) {
  std::lock_guard<std::mutex> lock(mutex_);
  Joined joined = latest_;
  joined.id = next_id_++;
  followers_.emplace(joined.id, std::move(fn));
  return joined;
}

void TakeEvents::Unsubscribe(int id) {
  std::lock_guard<std::mutex> lock(mutex_);
  followers_.erase(id);
}

void TakeEvents::Begin(const std::string& take_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  latest_ = Joined();
  latest_.take_id = take_id;
}

std::string TakeEvents::take_id() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return latest_.take_id;
}

void TakeEvents::Emit(v1::CaptureEvent e) {
  // Called under the lock, so that followers see the events in the order they were emitted and a follower that
  // subscribes sees each event either in its snapshot or through its function, never both and never neither.
  std::lock_guard<std::mutex> lock(mutex_);
  e.set_take_id(latest_.take_id);
  if (e.has_state()) latest_.state = e;
  if (e.has_progress()) latest_.progress = e;
  if (e.has_summary()) latest_.summary = e;
  for (auto& [id, fn] : followers_) fn(e);
}

}  // namespace stage::controller
