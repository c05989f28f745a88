// The simulated world's time, trigger bus and emission.
#include "stage/sim/world.h"

#include <algorithm>
#include <climits>
#include <cmath>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/clock.h"
#include "stage/common/logging.h"

namespace stage::sim {

World::World(const Dome& dome, WorldOptions options)
    : dome_(dome),
      options_(std::move(options)),
      base_(*timing::TimeBase::Create(std::max<uint32_t>(1, options_.slot_rate_hz))),
      emission_(dome, options_.rise_ns, options_.fall_ns) {}

World::~World() { Stop(); }

void World::Start() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (started_) return;
    started_ = true;
    if (options_.open_run) {
      runs_.push_back({0, options_.end_slot >= 0 ? options_.end_slot : INT64_MAX});
      if (options_.lockstep) current_ = 0;
    }
    // Real time without a given t0: slot 0 a moment from now.
    if (!options_.lockstep && options_.t0_ns == 0) {
      options_.t0_ns = RealClock(RealClock::Kind::kMonotonic).NowNs() + 100'000'000;
    }
  }
  changed_.notify_all();
  if (!options_.lockstep) {
    auto clock = timing::SlotClock::Create(
        {.slot_rate_hz = options_.slot_rate_hz, .t0_ns = options_.t0_ns, .slot_count = options_.end_slot});
    if (clock.ok()) {
      clock_ = std::move(*clock);
      clock_->AddListener([this](const timing::SlotEdge& e) { OnRealEdge(e); });
      // The clock's end (end_slot) with its last slots skipped: no edge follows to move the world past them.
      clock_->AddEndListener([this](int64_t) { OnRealEnd(); });
      (void)clock_->Start();
    }
  }
}

void World::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopped_ = true;
  }
  changed_.notify_all();
  if (clock_) clock_->Stop();
}

void World::OnRealEdge(const timing::SlotEdge& edge) {
  if (options_.before_real_edge) options_.before_real_edge(edge.slot);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (NextEdge(edge.slot) != edge.slot) {
      // A clock late by a slot or more skips edges: when it skipped a run's last slots, this silent edge is the first
      // after them, and the world has passed them: it stands at the run's last slot (delivered late, the ones before
      // it counted as missed, as inside a run). Without this the world would stand short of the run's end until the
      // next run, and whoever waits for the run to end would wait for ever.
      PassRunSlotsBefore(edge.slot);
      // The bus is silent between runs: from the end of the last run that is over, through this edge.
      int64_t ended = -1;
      for (const WorldRun& r : runs_) {
        if (r.end <= edge.slot) ended = r.end;
      }
      if (ended < 0) return;  // no run yet: nothing any node promised to build on
      quiet_from_ns_ = EdgeNs(ended);
      quiet_through_ns_ = EdgeNs(edge.slot);
    } else {
      current_ = edge.slot;
    }
  }
  changed_.notify_all();
}

void World::OnRealEnd() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    PassRunSlotsBefore(options_.end_slot);
  }
  changed_.notify_all();
}

void World::PassRunSlotsBefore(int64_t slot) {
  for (const WorldRun& r : runs_) {
    if (r.first < slot) current_ = std::max(current_, std::min(r.end, slot) - 1);
  }
}

int64_t World::NextEdge(int64_t slot) const {
  for (const WorldRun& r : runs_) {
    if (slot < r.end) return std::max(slot, r.first);
  }
  return -1;
}

WorldRun World::RunOf(int64_t slot) const {
  for (const WorldRun& r : runs_) {
    if (slot >= r.first && slot < r.end) return r;
  }
  return {slot, slot + 1};
}

int64_t World::EdgesBetween(int64_t from, int64_t to) const {
  int64_t n = 0;
  for (const WorldRun& r : runs_) n += std::max<int64_t>(0, std::min(to, r.end) - std::max(from, r.first));
  return n;
}

absl::StatusOr<WorldRun> World::PlanRun(int64_t count, int64_t lead_slots, int64_t align, int64_t min_first) const {
  if (count <= 0) return absl::InvalidArgumentError(absl::StrCat("a run of ", count, " slots"));
  std::lock_guard<std::mutex> lock(mutex_);
  if (!started_ || stopped_) return absl::FailedPreconditionError("the world is not running");
  const int64_t after = runs_.empty() ? 0 : runs_.back().end;
  if (after == INT64_MAX) return absl::FailedPreconditionError("the bus already runs without end");
  WorldRun run;
  run.first = after;
  if (!options_.lockstep) {
    const int64_t now = RealClock(RealClock::Kind::kMonotonic).NowNs();
    run.first = std::max(after, base_.SlotAtNs(std::max<int64_t>(0, now - options_.t0_ns)) + 1 + lead_slots);
  }
  run.first = std::max(run.first, min_first);
  if (align > 1) run.first = (run.first + align - 1) / align * align;
  run.end = run.first + count;
  return run;
}

absl::StatusOr<WorldRun> World::EndRun(int64_t align) {
  align = std::max<int64_t>(1, align);
  std::lock_guard<std::mutex> lock(mutex_);
  if (runs_.empty()) return absl::FailedPreconditionError("the bus has no run to end");
  WorldRun& run = runs_.back();
  if (run.end == INT64_MAX) return absl::FailedPreconditionError("the bus runs without end (stage-sim --world-slots)");
  if (current_ >= run.end - 1) {
    return absl::FailedPreconditionError(absl::StrCat("the run [", run.first, ", ", run.end, ") is over"));
  }
  // The next edge may already be on its way to a device in real time; the one after is the earliest safe end.
  const int64_t after = std::max(run.first, current_ + 1);
  const int64_t end = run.first + (after - run.first + align - 1) / align * align;
  if (end < run.end) {
    Logger("sim")->info("world: run [{}, {}) ends at slot {}", run.first, run.end, end);
    run.end = end;
  }
  return run;
}

absl::Status World::StartRun(const WorldRun& run) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!started_ || stopped_) return absl::FailedPreconditionError("the world is not running");
    // Asked again for the run it started (a caller whose first request's answer did not reach it): done already.
    if (!runs_.empty() && runs_.back().first == run.first && runs_.back().end == run.end &&
        runs_.back().driver == run.driver) {
      return absl::OkStatus();
    }
    const int64_t after = runs_.empty() ? 0 : runs_.back().end;
    if (run.first < after || run.end <= run.first) {
      return absl::FailedPreconditionError(
          absl::StrCat("run [", run.first, ", ", run.end, ") does not follow the last run (ends at ", after, ")"));
    }
    if (!options_.lockstep) {
      const int64_t now = RealClock(RealClock::Kind::kMonotonic).NowNs();
      if (EdgeNs(run.first) <= now) {
        return absl::FailedPreconditionError(
            absl::StrCat("run from slot ", run.first, " would start in the past; plan it with more lead"));
      }
    }
    runs_.push_back(run);
    MaybeAdvance();
  }
  changed_.notify_all();
  return absl::OkStatus();
}

absl::StatusOr<WorldRun> World::Run(int64_t count, int64_t lead_slots, int64_t align, int64_t min_first) {
  auto run = PlanRun(count, lead_slots, align, min_first);
  if (!run.ok()) return run.status();
  if (absl::Status s = StartRun(*run); !s.ok()) return s;
  return *run;
}

int World::Register(const std::string& name, int light_node) {
  std::lock_guard<std::mutex> lock(mutex_);
  Device d;
  d.name = name;
  d.light_node = light_node;
  // A device that joins late is done with what has passed.
  d.done_through = current_ - 1;
  devices_.push_back(d);
  if (light_node >= 0 && !watermarks_.count(light_node)) watermarks_[light_node] = INT64_MIN;
  return static_cast<int>(devices_.size()) - 1;
}

void World::Unregister(int device) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (device < 0 || device >= static_cast<int>(devices_.size()) || !devices_[device].active) return;
    Device& d = devices_[device];
    d.active = false;
    if (!runs_.empty() && !d.name.empty() && runs_.back().driver == d.name) {
      // The generator's line goes quiet: its run ends at the first slot no edge of which can be on its way.
      WorldRun& run = runs_.back();
      const int64_t end = std::max(run.first, current_ + 1);
      if (run.end != INT64_MAX && end < run.end) {
        Logger("sim")->warn("world: {}, which drives the run [{}, {}), left: the run ends at slot {}", d.name,
                            run.first, run.end, end);
        run.end = end;
      }
    }
    if (d.light_node >= 0) {
      // It emits nothing from what it last promised on, and holds no exposure up.
      int64_t& w = watermarks_[d.light_node];
      emission_.Dark(d.light_node, w == INT64_MIN ? 0 : w);
      w = INT64_MAX;
    }
    MaybeAdvance();
  }
  changed_.notify_all();
}

void World::MaybeAdvance() {
  if (!options_.lockstep || !started_ || stopped_) return;
  bool any = false;
  while (true) {
    bool all_done = true;
    for (const Device& d : devices_) {
      if (!d.active) continue;
      any = true;
      if (d.done_through < current_) all_done = false;
    }
    if (!any || !all_done) return;
    const int64_t next = NextEdge(current_ + 1);
    if (next < 0) return;  // between runs: the bus is silent
    if (options_.end_slot >= 0 && next >= options_.end_slot) return;
    current_ = next;
  }
}

std::optional<WorldEdge> World::WaitForEdge(int device, int64_t slot) {
  std::unique_lock<std::mutex> lock(mutex_);
  // By index: devices_ may grow while this thread waits.
  const size_t i = static_cast<size_t>(device);
  if (i >= devices_.size()) return std::nullopt;
  auto gone = [&] {
    return stopped_ || !devices_[i].active || (options_.end_slot >= 0 && std::max(slot, current_) >= options_.end_slot);
  };
  if (options_.lockstep) {
    devices_[i].done_through = std::max(devices_[i].done_through, slot - 1);
    MaybeAdvance();
    changed_.notify_all();
    // The first edge at or after `slot` (runs may leave gaps in the slot numbers).
    int64_t edge = -1;
    changed_.wait(lock, [&] {
      if (gone() || !started_) return gone();
      edge = NextEdge(slot);
      return edge >= 0 && current_ >= edge;
    });
    if (gone()) return std::nullopt;
    return WorldEdge{edge, EdgeNs(edge), 0, std::exchange(devices_[i].faults, {}), RunOf(edge)};
  }
  changed_.wait(lock, [&] { return gone() || (started_ && current_ >= slot && NextEdge(current_) == current_); });
  if (gone()) return std::nullopt;
  // Real time: the device gets the edge that is current; the ones it was too late for are counted.
  const int64_t now = current_;
  devices_[i].last_seen = now;
  return WorldEdge{now, EdgeNs(now), EdgesBetween(slot, now), std::exchange(devices_[i].faults, {}), RunOf(now)};
}

absl::Status World::InjectFault(const v1::SimFault& fault) {
  for (size_t u = 0; u < dome_.units.size(); ++u) {
    if (dome_.units[u].id != fault.target()) continue;
    SetUnitFault(u, {fault.dead(), static_cast<int64_t>(std::llround(fault.delay_us() * 1000))});
    return absl::OkStatus();
  }
  std::lock_guard<std::mutex> lock(mutex_);
  bool found = false;
  for (Device& d : devices_) {
    if (d.name != fault.target() || !d.active) continue;
    d.faults.push_back(fault);
    found = true;
  }
  if (!found) {
    return absl::NotFoundError(
        absl::StrCat("fault target \"", fault.target(), "\" is no LED unit of the dome and no device in the world"));
  }
  return absl::OkStatus();
}

void World::Done(int device, int64_t slot) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (device < 0 || device >= static_cast<int>(devices_.size())) return;
    Device& d = devices_[static_cast<size_t>(device)];
    d.done_through = std::max(d.done_through, slot);
    MaybeAdvance();
  }
  changed_.notify_all();
}

void World::ReportLevels(int light_node, int64_t t_ns, const std::vector<double>& levels, int64_t watermark_ns) {
  {
    // A node that has left is dark from its last promise on: a report racing its departure (its thread was between
    // an edge and this call) must not light it again, for ever.
    std::lock_guard<std::mutex> lock(mutex_);
    auto it = watermarks_.find(light_node);
    if (it != watermarks_.end() && it->second == INT64_MAX) return;
    emission_.SetLevels(light_node, t_ns, levels);
  }
  ReportWatermark(light_node, watermark_ns);
}

void World::ReportWatermark(int light_node, int64_t watermark_ns) {
  int64_t forget = INT64_MIN;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    int64_t& w = watermarks_[light_node];
    if (w != INT64_MAX) w = std::max(w, watermark_ns);
    // Forget in steps of a tenth of the history, behind the slowest node.
    int64_t slowest = INT64_MAX;
    for (const auto& [node, mark] : watermarks_) slowest = std::min(slowest, mark);
    if (slowest != INT64_MAX && slowest != INT64_MIN && options_.history_ns > 0) {
      const int64_t horizon = slowest - options_.history_ns;
      if (horizon > forgotten_before_ + options_.history_ns / 10) {
        forgotten_before_ = horizon;
        forget = horizon;
      }
    }
  }
  changed_.notify_all();
  if (forget != INT64_MIN) emission_.Forget(forget);
}

absl::StatusOr<EmitterLevels> World::Exposure(int64_t t0_ns, int64_t t1_ns) {
  {
    std::unique_lock<std::mutex> lock(mutex_);
    changed_.wait(lock, [&] {
      if (stopped_) return true;
      const bool quiet = t1_ns <= quiet_through_ns_;  // between runs (real time), see quiet_through_ns_
      for (const auto& [node, w] : watermarks_) {
        if (w < t1_ns && !(quiet && w >= quiet_from_ns_)) return false;
      }
      return true;
    });
    if (stopped_) return absl::CancelledError("the simulated world stopped");
    if (t0_ns < forgotten_before_) {
      return absl::OutOfRangeError(absl::StrFormat(
          "exposure at %.3f ms is older than the %.1f s of light the world keeps: the camera fell behind", t0_ns / 1e6,
          options_.history_ns / 1e9));
    }
  }
  return emission_.AverageLevels(t0_ns, t1_ns);
}

int64_t World::current_slot() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return current_;
}

std::optional<WorldRun> World::LastRun() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (runs_.empty()) return std::nullopt;
  return runs_.back();
}

}  // namespace stage::sim
