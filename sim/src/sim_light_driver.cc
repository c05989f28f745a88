// Simulated LED controller.
#include "stage/sim/sim_light_driver.h"

#include <algorithm>
#include <climits>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "stage/common/clock.h"
#include "stage/common/logging.h"
#include "stage/sim/world_client.h"
#include "stage/timing/time_base.h"

namespace stage::sim {

SimLightDriver::SimLightDriver(std::string node_id, uint32_t channel_count)
    : node_id_(std::move(node_id)), channel_count_(channel_count) {
  state_.channel_count = channel_count;
}

SimLightDriver::~SimLightDriver() { DetachWorld(); }

light::DriverDescription SimLightDriver::Describe() const { return {"sim", "sim:" + node_id_, channel_count_}; }

absl::Status SimLightDriver::LoadPatternTable(const light::PatternTable& table) {
  if (table.rows.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", node_id_, "\": pattern table has no rows"));
  }
  for (size_t r = 0; r < table.rows.size(); ++r) {
    if (table.rows[r].size() != channel_count_) {
      return absl::InvalidArgumentError(absl::StrCat("light node \"", node_id_, "\": pattern table row ", r, " has ",
                                                     table.rows[r].size(), " levels, the node has ", channel_count_,
                                                     " channels"));
    }
  }
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": load a table only when idle"));
  }
  table_ = table;
  table_loaded_ = true;
  return absl::OkStatus();
}

absl::Status SimLightDriver::Arm() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": arm only when idle"));
  }
  if (!table_loaded_) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": no pattern table loaded"));
  }
  state_.mode = light::DriverMode::kArmed;
  state_.current_row = -1;
  state_.steps = 0;
  start_at_ns_ = -1;
  start_requested_ns_ = -1;
  input_.table_first_slot = input_.table_first_edge_ns = -1;
  return absl::OkStatus();
}

absl::Status SimLightDriver::StartAt(int64_t first_edge_ns) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_.mode != light::DriverMode::kArmed) {
      return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": start a table only when armed"));
    }
    if (first_edge_ns != light::kStartNotYet && first_edge_ns == start_requested_ns_) return absl::OkStatus();  // retry
    if (first_edge_ns != light::kStartNotYet && input_.last_slot >= 0 &&
        input_.last_edge_ns >= first_edge_ns - half_period_ns_) {
      return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": the edge at ", first_edge_ns,
                                                        " ns has passed (the clock is at slot ", input_.last_slot,
                                                        ", ", input_.last_edge_ns, " ns)"));
    }
    start_at_ns_ = first_edge_ns;
    start_requested_ns_ = first_edge_ns;
    state_.current_row = -1;
    state_.steps = 0;
    input_.table_first_slot = input_.table_first_edge_ns = -1;
  }
  start_changed_.notify_all();
  return absl::OkStatus();
}

absl::StatusOr<light::ClockInput> SimLightDriver::SlotClockInput() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!attached_) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": not in a world: it sees no clock"));
  }
  light::ClockInput in = input_;
  // The run's last edge has come; in real time, an old last edge says the line went quiet too (a run ended early).
  in.running = in.last_slot >= 0 && in.last_slot < input_run_end_ - 1;
  const int64_t quiet = std::max(light::kQuietLineMinNs, light::kQuietLinePeriods * 2 * half_period_ns_);
  if (in.running && !lockstep_ && RealClock(RealClock::Kind::kMonotonic).NowNs() - in.last_edge_ns > quiet) {
    in.running = false;
  }
  return in;
}

absl::Status SimLightDriver::Disarm() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_.mode == light::DriverMode::kArmed) state_.mode = light::DriverMode::kIdle;
    state_.current_row = -1;
  }
  start_changed_.notify_all();
  return absl::OkStatus();
}

absl::Status SimLightDriver::Blackout() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    state_.mode = light::DriverMode::kBlackout;
    state_.current_row = -1;
  }
  start_changed_.notify_all();
  // In a real-time world the channels go dark now, as a board's do, not at the next edge: the world hears it before
  // this returns (a lockstep world has no "now" between edges: dark from the next one).
  std::lock_guard<std::mutex> lock(report_mutex_);
  if (world_thread_.joinable() && !detaching_.load() && !world_.world->lockstep()) {
    const int64_t t = std::max(RealClock(RealClock::Kind::kMonotonic).NowNs(), last_switch_ns_);
    world_.world->ReportLevels(world_.node_index, t, std::vector<double>(channel_count_, 0.0),
                               std::max(t, promised_ns_));
    last_switch_ns_ = t;
  }
  return absl::OkStatus();
}

absl::Status SimLightDriver::ResetBlackout() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode == light::DriverMode::kBlackout) state_.mode = light::DriverMode::kIdle;
  return absl::OkStatus();
}

light::DriverState SimLightDriver::State() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return state_;
}

void SimLightDriver::Step() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kArmed) return;
  state_.current_row = static_cast<int>(state_.steps % table_.rows.size());
  ++state_.steps;
}

light::ChannelLevels SimLightDriver::Outputs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kArmed || state_.current_row < 0) {
    return light::ChannelLevels(channel_count_, 0);
  }
  return table_.rows[static_cast<size_t>(state_.current_row)];
}

absl::Status SimLightDriver::AttachWorld(const SimLightWorld& world) {
  if (world.world == nullptr) return absl::InvalidArgumentError("no world to attach to");
  if (world_thread_.joinable()) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": already in the world"));
  }
  auto device = world.world->Join(node_id_, world.node_index);
  if (!device.ok()) return device.status();
  world_ = world;
  world_device_ = *device;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    attached_ = true;
    lockstep_ = world.world->lockstep();
  }
  world_thread_ = std::thread([this, d = *device] { WorldLoop(d); });
  return absl::OkStatus();
}

void SimLightDriver::DetachWorld() {
  if (!world_thread_.joinable()) return;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    detaching_.store(true);
    attached_ = false;
  }
  start_changed_.notify_all();
  world_.world->Leave(world_device_);
  world_thread_.join();
}

void SimLightDriver::WorldLoop(int device) {
  auto base = timing::TimeBase::Create(world_.world->slot_rate_hz());
  if (!base.ok()) {
    Logger("sim")->error("light node {}: {}", node_id_, base.status().message());
    return;
  }
  std::vector<double> levels(channel_count_);
  const int64_t half_period = base->SlotStartNs(1) / 2;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    half_period_ns_ = half_period;
  }
  int64_t slot = 0;
  while (!detaching_.load()) {
    if (world_.world->lockstep()) HoldForStart();
    auto edge = world_.world->WaitForEdge(device, slot);
    if (!edge) break;
    for (const v1::SimFault& fault : edge->faults) {
      if (fault.has_delay_us()) world_.fault_delay_ns = static_cast<int64_t>(std::llround(fault.delay_us() * 1e3));
      if (fault.has_crash_at_s()) world_.crash_at_ns = static_cast<int64_t>(std::llround(fault.crash_at_s() * 1e9));
      // Extra pulses on the board's step input: its table runs ahead of the bus from now on.
      for (int i = 0; i < fault.extra_steps(); ++i) Step();
      Logger("sim")->warn("light node {}: fault injected: {}", node_id_, fault.ShortDebugString());
    }
    const int64_t delay = world_.switch_delay_ns + world_.extra_delay_ns + world_.fault_delay_ns;
    const int64_t since_slot0_ns = edge->time_ns - world_.world->t0_ns();
    if (world_.on_edge) world_.on_edge(since_slot0_ns);
    if (world_.crash_at_ns >= 0 && since_slot0_ns >= world_.crash_at_ns) {
      Logger("sim")->warn("light node {}: crashes at slot {} (fault)", node_id_, edge->slot);
      if (world_.on_crash) world_.on_crash();
      world_.world->Leave(device);
      break;
    }
    // A board steps on every edge; a process that saw some late catches up, so the table stays in phase.
    StepOnEdge(edge->slot, edge->time_ns, edge->missed, edge->run.end, half_period);
    if (edge->missed > 0) late_edges_.fetch_add(static_cast<uint64_t>(edge->missed));
    std::lock_guard<std::mutex> report(report_mutex_);  // a blackout reports between two edges, never inside one
    const light::ChannelLevels out = Outputs();
    for (size_t c = 0; c < levels.size(); ++c) levels[c] = out[c] / 65535.0;
    // A delay that shrank at run time cannot take back light already promised: the switch waits for the promise.
    const int64_t switch_ns = std::max({edge->time_ns + delay, promised_ns_, last_switch_ns_});
    promised_ns_ =
        std::max(switch_ns, edge->time_ns + base->SlotStartNs(edge->slot + 1) - base->SlotStartNs(edge->slot) + delay);
    world_.world->ReportLevels(world_.node_index, switch_ns, levels, promised_ns_);
    last_switch_ns_ = switch_ns;
    slot = edge->slot + 1;
  }
}

void SimLightDriver::StepOnEdge(int64_t slot, int64_t time_ns, int64_t missed, int64_t run_end, int64_t half_period_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  input_.last_slot = slot;
  input_.last_edge_ns = time_ns;
  input_run_end_ = run_end;
  if (state_.mode != light::DriverMode::kArmed) return;
  if (start_at_ns_ >= 0) {
    // The table waits for its planned first edge, dark.
    if (start_at_ns_ == light::kStartNotYet || time_ns < start_at_ns_ - half_period_ns) {
      state_.current_row = -1;
      return;
    }
    start_at_ns_ = -1;
    input_.table_first_slot = slot;
    input_.table_first_edge_ns = time_ns;
    missed = 0;  // the table starts here: nothing to catch up
  }
  // A board steps on every edge; a process that saw some late catches up, so the table stays in phase.
  state_.steps += static_cast<uint64_t>(missed);
  state_.current_row = static_cast<int>(state_.steps % table_.rows.size());
  ++state_.steps;
}

void SimLightDriver::HoldForStart() {
  std::unique_lock<std::mutex> lock(mutex_);
  start_changed_.wait(lock, [&] {
    return detaching_.load() || state_.mode != light::DriverMode::kArmed || start_at_ns_ != light::kStartNotYet;
  });
}

}  // namespace stage::sim
