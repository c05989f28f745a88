// The console's event stream: every event (a stage status, a take's progress, an alarm, a log line) gets the next id
// and waits in a ring for the browsers that follow the stream (Server-Sent Events). A browser that reconnects with
// Last-Event-ID resumes after it; one that was away longer than the ring holds is told it missed some (a gap).
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <mutex>
#include <string>
#include <vector>

namespace stage::console {

struct ConsoleEvent {
  uint64_t id = 0;
  // The SSE event name: "status", "take", "alarm", "log".
  std::string type;
  // One line of JSON.
  std::string data;
};

class EventLog {
 public:
  // Keeps the last `capacity` events (at least 1).
  explicit EventLog(size_t capacity);

  // Appends an event and wakes the followers; returns its id (1, 2, ...). Newlines in `data` become spaces (an SSE
  // data line ends at one).
  uint64_t Publish(std::string type, std::string data);

  // The events after id `after`, oldest first: those in the ring now, or, when there are none, those that come within
  // `timeout` (an empty result then). `*gap` says events after `after` were dropped from the ring before they were
  // read, or that `after` is an id this log never gave (a console restarted): the follower should fetch the state
  // afresh. After Close(), returns at once.
  std::vector<ConsoleEvent> After(uint64_t after, std::chrono::milliseconds timeout, bool* gap) const;

  // The id of the last event published (0: none).
  uint64_t last_id() const;

  // Wakes every follower; After() no longer waits.
  void Close();

 private:
  size_t capacity_;
  mutable std::mutex mutex_;
  mutable std::condition_variable published_;
  std::deque<ConsoleEvent> ring_;  // guarded by mutex_
  uint64_t last_id_ = 0;           // guarded by mutex_
  bool closed_ = false;            // guarded by mutex_
};

// One event in the text/event-stream format: "id: N\nevent: TYPE\ndata: DATA\n\n", a "data:" line for each line of
// DATA.
std::string FormatServerSentEvent(const ConsoleEvent& event);

}  // namespace stage::console
