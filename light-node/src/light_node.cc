// Light node logic.
#include "light_node.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
#include "stage/timing/led_load.h"

namespace stage::light {

absl::StatusOr<std::unique_ptr<LightNode>> LightNode::Create(const v1::LightNodeConfig& config,
                                                             std::unique_ptr<LightDriver> driver, std::string rig_hash,
                                                             LightNodeOptions options) {
  if (driver->Describe().channel_count != config.channel_count()) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", config.id(), "\": driver has ",
                                                      driver->Describe().channel_count,
                                                      " channels, rig says channel_count ", config.channel_count()));
  }
  if (!(options.slot_rate_hz > 0) || !(options.take_length_s > 0) || options.heartbeat_timeout_ms < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("light node \"", config.id(), "\": slot rate, take length and heartbeat timeout must be > 0"));
  }
  auto node = std::unique_ptr<LightNode>(new LightNode(config, std::move(driver), std::move(rig_hash), options));
  node->metrics_ =
      metrics::Registry::Default().AddCollector([n = node.get()](metrics::Writer& w) { n->CollectMetrics(w); });
  return node;
}

void LightNode::CollectMetrics(metrics::Writer& w) const {
  const v1::LightStats s = Stats();
  const metrics::Labels node = {{"node", config_.id()}};
  for (const auto& [mode, name] : {std::pair{v1::LIGHT_MODE_IDLE, "idle"},
                                   {v1::LIGHT_MODE_ARMED, "armed"},
                                   {v1::LIGHT_MODE_BLACKOUT, "blackout"}}) {
    w.Gauge("stage_light_mode",
            "The light node's mode: 1 for the current one (idle, armed, blackout), 0 for the others",
            {{"node", config_.id()}, {"mode", name}}, s.mode() == mode ? 1 : 0);
  }
  w.Gauge("stage_light_table_steps", "Rows the pattern table has stepped through since the node was armed", node,
          static_cast<double>(s.steps()));
  w.Gauge("stage_light_faults", "Faults the LED board reports now", node, s.faults_size());
  if (s.temperature_c() != 0) {
    w.Gauge("stage_light_temperature_celsius", "The LED board's temperature", node, s.temperature_c());
  }
  const TableLoad load{.duty = s.max_channel_duty(), .peak = s.max_thermal_load()};
  uint64_t trips = 0;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    trips = watchdog_trips_;
  }
  w.Gauge("stage_light_duty_ratio",
          "The armed table's highest mean drive of one channel, of full drive (0 when not armed; the arming check "
          "holds it under the channel's max_duty_cycle)",
          node, load.duty);
  w.Gauge("stage_light_thermal_load_ratio",
          "The armed table's highest thermal load of one channel during the take, of full drive (0 when not armed)",
          node, load.peak);
  w.Counter("stage_light_watchdog_trips_total", "Blackouts because the controller's heartbeat stopped", node,
            static_cast<double>(trips));
  if (s.has_slot_clock()) {
    const v1::MeasuredSlotClock& c = s.slot_clock();
    w.Gauge("stage_light_slot_clock_lost_edges", "Slot clock edges that never reached the node since arming", node,
            static_cast<double>(c.lost_edges()));
    w.Gauge("stage_light_step_latency_max_seconds", "Longest time from a slot edge to the outputs set, since arming",
            node, c.max_step_latency_us() * 1e-6);
  }
}

LightNode::LightNode(v1::LightNodeConfig config, std::unique_ptr<LightDriver> driver, std::string rig_hash,
                     LightNodeOptions options)
    : config_(std::move(config)), driver_(std::move(driver)), rig_hash_(std::move(rig_hash)), options_(options) {
  slot_clock_ = driver_->slot_clock();
  watchdog_ = std::thread([this] { Watchdog(); });
}

LightNode::~LightNode() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  watchdog_.join();
  if (absl::Status s = driver_->Blackout(); !s.ok()) {
    Logger("light.node")->error("{}: blackout on shutdown failed: {}", config_.id(), s.message());
  }
}

v1::NodeInfo LightNode::Info() const {
  return MakeNodeInfo(config_.id(), v1::NODE_KIND_LIGHT, v1::CAMERA_ROLE_UNSPECIFIED, driver_->Describe().backend,
                      rig_hash_);
}

v1::LightStats LightNode::Stats() const {
  DriverState state = driver_->State();
  v1::LightStats stats;
  switch (state.mode) {
    case DriverMode::kIdle:
      stats.set_mode(v1::LIGHT_MODE_IDLE);
      break;
    case DriverMode::kArmed:
      stats.set_mode(v1::LIGHT_MODE_ARMED);
      break;
    case DriverMode::kBlackout:
      stats.set_mode(v1::LIGHT_MODE_BLACKOUT);
      break;
  }
  stats.set_steps(state.steps);
  stats.set_current_row(state.current_row < 0 ? 0 : static_cast<uint32_t>(state.current_row));
  for (const std::string& f : state.faults) stats.add_faults(f);
  for (const std::string& f : state.take_faults) stats.add_take_faults(f);
  if (state.temperature_c) stats.set_temperature_c(*state.temperature_c);
  if (state.edges) {
    stats.set_slot_edges(state.edges->count);
    v1::MeasuredSlotClock* clock = stats.mutable_slot_clock();
    clock->set_edges(state.edges->count);
    clock->set_period_mean_us(state.edges->period_mean_ns / 1e3);
    clock->set_period_max_deviation_us(state.edges->period_max_deviation_ns / 1e3);
    clock->set_max_step_latency_us(static_cast<double>(state.edges->max_step_latency_ns) / 1e3);
    clock->set_lost_edges(state.edges->lost_edges);
  }
  std::lock_guard<std::mutex> lock(mutex_);
  if (state.mode == DriverMode::kArmed) {
    stats.set_max_channel_duty(armed_load_.duty);
    stats.set_max_thermal_load(armed_load_.peak);
  }
  if (state.mode == DriverMode::kBlackout) {
    stats.set_blackout_reason(blackout_reason_.empty() ? "blackout by the board itself (see faults)"
                                                       : blackout_reason_);
  }
  return stats;
}

absl::Status LightNode::CheckLoad(const PatternTable& table, int64_t take_slots, TableLoad* most) const {
  const double slot_s = 1.0 / options_.slot_rate_hz;
  std::vector<double> drive(table.rows.size());
  for (const v1::LedUnit& u : config_.units()) {
    const v1::LedLimits& limits = u.has_limits() ? u.limits() : config_.unit_limits();
    for (const auto& [ch, emitter] : {std::pair{u.parallel_channel(), "parallel"}, {u.cross_channel(), "cross"}}) {
      if (ch >= config_.channel_count()) continue;
      for (size_t r = 0; r < table.rows.size(); ++r) drive[r] = table.rows[r][ch] / 65535.0;
      const timing::LedLoad load = timing::ComputeLedLoad(drive, slot_s, limits.thermal_time_constant_s(), take_slots);
      const double limit = limits.max_duty_cycle();
      most->duty = std::max(most->duty, load.duty);
      most->peak = std::max(most->peak, load.peak);
      if (load.duty > limit + 1e-12) {
        return absl::FailedPreconditionError(absl::StrFormat(
            "light node \"%s\": channel %d (%s %s) would average %.3f of full drive over the %d-row table, above "
            "its max_duty_cycle %g; not armed",
            config_.id(), ch, u.id(), emitter, load.duty, table.rows.size(), limit));
      }
      if (load.peak > limit + 1e-12) {
        return absl::FailedPreconditionError(absl::StrFormat(
            "light node \"%s\": channel %d (%s %s) would reach a thermal load of %.3f of full drive during the "
            "%.2f s take (thermal_time_constant_s %g), above its max_duty_cycle %g; not armed",
            config_.id(), ch, u.id(), emitter, load.peak, take_slots * slot_s, limits.thermal_time_constant_s(),
            limit));
      }
    }
  }
  return absl::OkStatus();
}

absl::Status LightNode::Arm(const v1::ArmLightRequest& request) {
  // One arming at a time; asked again for the take it is armed for (a controller that did not hear the answer), the
  // answer is the same and the table is not loaded twice.
  std::lock_guard<std::mutex> arming(arm_mutex_);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (watching_ && !request.take_id().empty() && take_id_ == request.take_id() &&
        driver_->State().mode == DriverMode::kArmed) {
      heartbeat_.Beat(std::chrono::steady_clock::now());
      return absl::OkStatus();
    }
  }
  const v1::PatternTable& table = request.table();
  PatternTable t;
  t.pattern_set = table.pattern_set();
  for (int r = 0; r < table.rows_size(); ++r) {
    const v1::PatternRow& row = table.rows(r);
    t.row_names.push_back(row.name());
    if (static_cast<uint32_t>(row.levels_size()) != config_.channel_count()) {
      return absl::InvalidArgumentError(absl::StrCat("light node \"", config_.id(), "\": row ", r, " (", row.name(),
                                                     ") has ", row.levels_size(), " levels, the node has ",
                                                     config_.channel_count(), " channels"));
    }
    ChannelLevels levels;
    for (int c = 0; c < row.levels_size(); ++c) {
      if (row.levels(c) > 65535) {
        return absl::InvalidArgumentError(absl::StrCat("light node \"", config_.id(), "\": row ", r, " (", row.name(),
                                                       ") channel ", c, ": level ", row.levels(c), " is above 65535"));
      }
      levels.push_back(static_cast<uint16_t>(row.levels(c)));
    }
    t.rows.push_back(std::move(levels));
  }
  if (t.rows.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", config_.id(), "\": the pattern table has no rows"));
  }
  const int64_t take_slots = request.take_slots() > 0
                                 ? request.take_slots()
                                 : static_cast<int64_t>(std::ceil(options_.take_length_s * options_.slot_rate_hz));
  TableLoad load;
  if (absl::Status s = CheckLoad(t, take_slots, &load); !s.ok()) {
    Logger("light.node")->error("{}", s.message());
    return s;
  }
  if (driver_->State().mode == DriverMode::kBlackout) {
    std::lock_guard<std::mutex> lock(mutex_);
    return absl::FailedPreconditionError(absl::StrCat("light node \"", config_.id(), "\": in blackout (",
                                                      blackout_reason_.empty() ? "by the hardware" : blackout_reason_,
                                                      "); reset it first (stagectl estop --reset)"));
  }
  if (driver_->State().mode == DriverMode::kArmed) {
    if (absl::Status s = driver_->Disarm(); !s.ok()) return s;
  }
  if (absl::Status s = driver_->LoadPatternTable(t); !s.ok()) return s;
  if (absl::Status s = driver_->Arm(); !s.ok()) return s;
  if (request.start_at_planned_edge()) {
    // The clock runs free: dark until StartTable names the first row's edge. A driver that cannot wait is disarmed.
    if (absl::Status s = driver_->StartAt(kStartNotYet); !s.ok()) {
      (void)driver_->Disarm();
      return absl::FailedPreconditionError(absl::StrCat("light node \"", config_.id(), "\": ", s.message()));
    }
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    watching_ = true;
    armed_load_ = load;
    take_id_ = request.take_id();
    heartbeat_ = HeartbeatWatch(std::chrono::milliseconds(
        request.heartbeat_timeout_ms() > 0 ? request.heartbeat_timeout_ms() : options_.heartbeat_timeout_ms));
    heartbeat_.Beat(std::chrono::steady_clock::now());
  }
  wake_.notify_all();
  Logger("light.node")
      ->info("{}: armed for take {} ({} rows) on {}", config_.id(), request.take_id(), t.rows.size(),
             driver_->Describe().device);
  return absl::OkStatus();
}

absl::Status LightNode::StartTable(const std::string& take_id, int64_t first_edge_ns) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (take_id_ != take_id) {
      return absl::FailedPreconditionError(absl::StrCat("light node \"", config_.id(), "\": not armed for take \"",
                                                        take_id, "\"", take_id_.empty() ? "" : " (armed for \"",
                                                        take_id_, take_id_.empty() ? "" : "\")"));
    }
    if (!watching_) {
      // Armed for this take once, and no more: say what ended it (a blackout's reason, the watchdog's included).
      return absl::FailedPreconditionError(absl::StrCat(
          "light node \"", config_.id(), "\": no longer armed for take \"", take_id, "\": ",
          blackout_reason_.empty() ? std::string("disarmed") : absl::StrCat("in blackout (", blackout_reason_, ")")));
    }
  }
  if (absl::Status s = driver_->StartAt(first_edge_ns); !s.ok()) {
    return absl::Status(s.code(), absl::StrCat("light node \"", config_.id(), "\": ", s.message()));
  }
  Logger("light.node")
      ->info("{}: take {}: the table starts at the edge at {} ns", config_.id(), take_id, first_edge_ns);
  return absl::OkStatus();
}

absl::StatusOr<v1::ClockInput> LightNode::ClockInput() const {
  auto in = driver_->SlotClockInput();
  if (!in.ok())
    return absl::Status(in.status().code(), absl::StrCat("light node \"", config_.id(), "\": ", in.status().message()));
  v1::ClockInput out;
  out.set_running(in->running);
  out.set_last_slot(in->last_slot);
  out.set_last_edge_ns(in->last_edge_ns);
  out.set_table_first_slot(in->table_first_slot);
  out.set_table_first_edge_ns(in->table_first_edge_ns);
  return out;
}

absl::Status LightNode::Disarm(const std::string& take_id) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    watching_ = false;
  }
  if (driver_->State().mode != DriverMode::kArmed) return absl::OkStatus();
  Logger("light.node")->info("{}: disarmed after take {}", config_.id(), take_id);
  return driver_->Disarm();
}

absl::Status LightNode::Blackout(const std::string& reason) {
  {
    // The reason first: a status read while the driver goes dark already says why.
    std::lock_guard<std::mutex> lock(mutex_);
    watching_ = false;
    blackout_reason_ = reason;
  }
  absl::Status s = driver_->Blackout();
  if (s.ok()) {
    Logger("light.node")->warn("{}: blackout ({})", config_.id(), reason);
  } else {
    Logger("light.node")->error("{}: blackout ({}) NOT confirmed: {}", config_.id(), reason, s.message());
  }
  return s;
}

absl::Status LightNode::ResetBlackout() {
  if (absl::Status s = driver_->ResetBlackout(); !s.ok()) return s;
  std::lock_guard<std::mutex> lock(mutex_);
  blackout_reason_.clear();
  Logger("light.node")->info("{}: blackout reset", config_.id());
  return absl::OkStatus();
}

void LightNode::Heartbeat(const std::string& take_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  heartbeat_.Beat(std::chrono::steady_clock::now());
}

uint64_t LightNode::watchdog_trips() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return watchdog_trips_;
}

void LightNode::Watchdog() {
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stopping_) {
    if (!watching_) {
      wake_.wait(lock, [this] { return stopping_ || watching_; });
      continue;
    }
    const auto now = std::chrono::steady_clock::now();
    if (!heartbeat_.Expired(now)) {
      wake_.wait_until(lock, heartbeat_.NextLook(now));
      continue;
    }
    const std::string reason = absl::StrFormat("controller heartbeat lost: none for %d ms while armed for take %s",
                                               heartbeat_.timeout().count(), take_id_);
    watching_ = false;
    ++watchdog_trips_;
    lock.unlock();
    Blackout(reason).IgnoreError();  // logged there
    lock.lock();
  }
}

absl::StatusOr<v1::SlotClockRun> LightNode::RunSlotClock(const v1::SlotClockRunRequest& request) {
  if (slot_clock_ == nullptr) return NoSlotClock();
  if (request.slots() <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("slot clock run: slots ", request.slots(), " is not above 0"));
  }
  auto run = slot_clock_->Run(request);
  if (run.ok() && !request.plan_only()) {
    Logger("light.node")
        ->info("{}: slot clock run [{}, {}) started for {}", config_.id(), run->first_slot(), run->end_slot(),
               request.requested_by().empty() ? "an unnamed caller" : request.requested_by());
  }
  return run;
}

absl::StatusOr<v1::SlotClockRun> LightNode::EndSlotClock(int64_t align_slots) {
  if (slot_clock_ == nullptr) return NoSlotClock();
  auto run = slot_clock_->End(align_slots);
  if (run.ok()) Logger("light.node")->info("{}: slot clock run ends at slot {}", config_.id(), run->end_slot());
  return run;
}

absl::StatusOr<v1::SlotClockRun> LightNode::GetSlotClock() {
  if (slot_clock_ == nullptr) return NoSlotClock();
  return slot_clock_->Get();
}

absl::Status LightNode::NoSlotClock() const {
  return absl::FailedPreconditionError(absl::StrCat(
      "light node ", config_.id(),
      " runs no slot clock: it is not the rig's timing.sync_generator, or its backend cannot run a planned clock (its "
      "log says which)"));
}

}  // namespace stage::light
