// The events of the session's current take, to everyone who follows it: the Capture or Arm call that started it and
// any number of WatchTake calls, which may come and go while the take runs (a client that goes away stops watching,
// not the take). Every event is stamped with the take's id. A follower who joins late starts from the take's latest
// state and progress; one who joins after its summary gets the summary.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <string>

#include "stage/v1/controller.pb.h"

namespace stage::controller {

using CaptureEventFn = std::function<void(const v1::CaptureEvent&)>;

class TakeEvents {
 public:
  // Where a follower joins: the take, and what it has said so far that a follower needs to start from.
  struct Joined {
    int id = 0;
    std::string take_id;                       // empty: no take yet
    std::optional<v1::CaptureEvent> state;     // its latest state
    std::optional<v1::CaptureEvent> progress;  // its latest progress
    std::optional<v1::CaptureEvent> summary;   // set once it has ended
  };

  // `fn` gets every event from now on (on the take's threads; it must not block for long). The returned snapshot is
  // taken atomically with the subscription, so no event falls between the two.
  Joined Subscribe(CaptureEventFn fn);
  void Unsubscribe(int id);

  // A new take: its events carry `take_id`, and late followers start from scratch.
  void Begin(const std::string& take_id);
  // Stamps the take's id on `e`, keeps it if it is a state, progress or summary, and hands it to every follower.
  void Emit(v1::CaptureEvent e);
  // The take's id, or empty before the first take.
  std::string take_id() const;

 private:
  mutable std::mutex mutex_;
  std::map<int, CaptureEventFn> followers_;  // guarded by mutex_
  int next_id_ = 1;                          // guarded by mutex_
  Joined latest_;                            // guarded by mutex_ (its id unused)
};

// A caller that follows the take's events for as long as it lives (a Capture or Arm call); none for a null `fn`.
class Following {
 public:
  Following(TakeEvents* events, const CaptureEventFn& fn) : events_(events) {
    if (fn) id_ = events_->Subscribe(fn).id;
  }
  ~Following() {
    if (id_ != 0) events_->Unsubscribe(id_);
  }
  Following(const Following&) = delete;
  Following& operator=(const Following&) = delete;

 private:
  TakeEvents* events_;
  int id_ = 0;
};

}  // namespace stage::controller
