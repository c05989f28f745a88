// When a running take's frames are all in: see take_watch.h.
#include "take_watch.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace stage::controller {
namespace {

// Where the slot clock cannot say how far it has got, a take whose cameras owe nothing ends after the drain and
// this much more of silence (the clock may still be on its way to the next frame's triggers).
constexpr std::chrono::seconds kUnknownClockGrace{5};

}  // namespace

TakeWatch::TakeWatch(TakeWatchOptions options, TimePoint start) : options_(options), quiet_since_(start) {}

void TakeWatch::Restart(TimePoint now) { quiet_since_ = now; }

bool TakeWatch::Fold(const TakeSnapshot& snapshot) {
  bool moved = false;
  for (const TakeSnapshot::Camera& c : snapshot.cameras) {
    auto [it, added] = cameras_.try_emplace(c.id);
    Known& k = it->second;
    if (c.down && !k.down) {
      k.down = true;
      k.owed = 0;  // a node that is gone delivers nothing more
      moved = true;
    }
    if (!c.answered) continue;
    k.down = false;
    if (c.received > k.received || c.work > k.work) moved = true;
    k.received = std::max(k.received, c.received);
    k.work = std::max(k.work, c.work);
    k.owed = c.owed;
    k.activity = c.activity;
  }
  if (snapshot.clock_edges) {
    if (!clock_edges_ || *snapshot.clock_edges != *clock_edges_ || snapshot.clock_run_slots != clock_run_slots_) {
      moved = true;
    }
    clock_edges_ = snapshot.clock_edges;
    clock_run_slots_ = snapshot.clock_run_slots;
  }
  return moved;
}

void TakeWatch::Describe(const TakeSnapshot& snapshot) {
  std::vector<std::string> parts;
  int owing = 0;
  for (const TakeSnapshot::Camera& c : snapshot.cameras) {
    const Known& k = cameras_[c.id];
    if (k.down || k.owed <= 0) continue;
    if (++owing > 3) continue;  // the first three by name; the count says the rest
    parts.push_back(absl::StrCat(c.id, " owes ", k.owed, k.owed == 1 ? " frame" : " frames",
                                 k.activity.empty() ? "" : absl::StrCat(" (", k.activity, ")"),
                                 c.answered ? "" : " [not answering]"));
  }
  if (owing > 3) parts.push_back(absl::StrCat("and ", owing - 3, " more camera(s)"));
  if (clock_edges_ && *clock_edges_ < clock_run_slots_) {
    parts.push_back(absl::StrCat("the slot clock: ", *clock_edges_, " of ", clock_run_slots_, " edges"));
  }
  waiting_for_ = absl::StrJoin(parts, "; ");
}

TakeVerdict TakeWatch::Observe(const TakeSnapshot& snapshot, TimePoint now) {
  if (Fold(snapshot)) quiet_since_ = now;
  int64_t expected = 0, received = 0;
  owed_ = 0;
  for (const TakeSnapshot::Camera& c : snapshot.cameras) {
    const Known& k = cameras_[c.id];
    expected += c.expected;
    received += std::min(k.received, c.expected);
    if (!k.down) owed_ += std::max<int64_t>(0, k.owed);
  }
  Describe(snapshot);
  if (received >= expected) return TakeVerdict::kComplete;
  const auto quiet = now - quiet_since_;
  if (owed_ == 0) {
    if (clock_edges_ && *clock_edges_ >= clock_run_slots_) {
      return quiet >= options_.drain ? TakeVerdict::kDrained : TakeVerdict::kUnderWay;
    }
    if (!clock_edges_ && quiet >= options_.drain + kUnknownClockGrace) return TakeVerdict::kDrained;
  }
  if (options_.stall.count() > 0 && quiet >= options_.stall) return TakeVerdict::kStalled;
  return TakeVerdict::kUnderWay;
}

}  // namespace stage::controller
