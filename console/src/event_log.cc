#include "event_log.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace stage::console {

EventLog::EventLog(size_t capacity) : capacity_(std::max<size_t>(1, capacity)) {}

uint64_t EventLog::Publish(std::string type, std::string data) {
  std::replace(data.begin(), data.end(), '\n', ' ');
  std::replace(data.begin(), data.end(), '\r', ' ');
  uint64_t id = 0;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    id = ++last_id_;
    ring_.push_back({id, std::move(type), std::move(data)});
    while (ring_.size() > capacity_) ring_.pop_front();
  }
  published_.notify_all();
  return id;
}

std::vector<ConsoleEvent> EventLog::After(uint64_t after, std::chrono::milliseconds timeout, bool* gap) const {
  std::unique_lock<std::mutex> lock(mutex_);
  // An id from before this console started (a browser that followed the one before it): everything is new.
  const bool stale = after > last_id_;
  if (stale) after = 0;
  published_.wait_for(lock, timeout, [&] { return closed_ || last_id_ > after; });
  std::vector<ConsoleEvent> out;
  *gap = stale || (!ring_.empty() && after + 1 < ring_.front().id);
  for (const ConsoleEvent& e : ring_) {
    if (e.id > after) out.push_back(e);
  }
  return out;
}

uint64_t EventLog::last_id() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return last_id_;
}

void EventLog::Close() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    closed_ = true;
  }
  published_.notify_all();
}

std::string FormatServerSentEvent(const ConsoleEvent& event) {
  std::string out = absl::StrCat("id: ", event.id, "\nevent: ", event.type, "\n");
  // A line of data each: the browser joins them with newlines.
  for (absl::string_view line : absl::StrSplit(event.data, absl::ByAnyChar("\r\n"))) {
    absl::StrAppend(&out, "data: ", line, "\n");
  }
  out += "\n";
  return out;
}

}  // namespace stage::console
