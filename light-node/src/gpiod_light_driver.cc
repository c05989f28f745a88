// LED channels on GPIO lines, stepping on the slot clock.
#include "gpiod_light_driver.h"

#include <algorithm>
#include <cmath>
#include <set>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/logging.h"
#include "take_faults.h"

namespace stage::light {

// The driver's clock output as the node's slot clock.
class GpiodSlotClock final : public SlotClockGenerator {
 public:
  explicit GpiodSlotClock(GpiodLightDriver* driver) : driver_(driver) {}
  std::string Describe() const override {
    const DriverDescription d = driver_->Describe();
    return absl::StrCat("the gpiod clock output of ", d.device);
  }
  absl::StatusOr<v1::SlotClockRun> Run(const v1::SlotClockRunRequest& request) override {
    return driver_->RunClock(request);
  }
  absl::StatusOr<v1::SlotClockRun> End(int64_t align_slots) override { return driver_->EndClock(align_slots); }
  absl::StatusOr<v1::SlotClockRun> Get() override { return driver_->ClockRun(); }

 private:
  GpiodLightDriver* driver_;
};

absl::Status GpiodDriverOptions::Validate() const {
  const std::string who = absl::StrCat("light node \"", node_id, "\": ");
  if (channel_count < 1 || channel_count > 4096) {
    return absl::InvalidArgumentError(absl::StrCat(who, "channel_count ", channel_count, " is not in 1..4096"));
  }
  if (lines_per_channel < 1 || lines_per_channel > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat(who, "gpiod.lines_per_channel ", lines_per_channel, " is not in 1..16"));
  }
  if (lines.outputs.size() != static_cast<size_t>(channel_count) * lines_per_channel) {
    return absl::InvalidArgumentError(absl::StrCat(who, "gpiod.channel_lines has ", lines.outputs.size(),
                                                   " lines; channel_count x lines_per_channel is ",
                                                   channel_count * lines_per_channel));
  }
  std::set<uint32_t> seen;
  for (size_t i = 0; i < lines.outputs.size(); ++i) {
    if (!seen.insert(lines.outputs[i]).second) {
      return absl::InvalidArgumentError(
          absl::StrCat(who, "gpiod.channel_lines[", i, "]: line ", lines.outputs[i], " is listed twice"));
    }
  }
  if (!lines.slot_clock_line) {
    return absl::InvalidArgumentError(
        absl::StrCat(who, "gpiod.slot_clock_line is required (the node steps on it, or drives it)"));
  }
  if (seen.count(*lines.slot_clock_line) > 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(who, "gpiod.slot_clock_line ", *lines.slot_clock_line, " is also a channel line"));
  }
  if (!(slot_rate_hz > 0 && slot_rate_hz <= 100'000)) {
    return absl::InvalidArgumentError(absl::StrCat(who, "slot_rate_hz ", slot_rate_hz, " is not in (0, 100000]"));
  }
  if (lines.drives_slot_clock && slot_rate_hz != std::round(slot_rate_hz)) {
    return absl::InvalidArgumentError(
        absl::StrCat(who, "generating the slot clock needs a whole slot_rate_hz (", slot_rate_hz, ")"));
  }
  if (!(clock_duty > 0 && clock_duty <= 0.5)) {
    return absl::InvalidArgumentError(absl::StrCat(who, "clock_duty ", clock_duty, " is not in (0, 0.5]"));
  }
  if (edge_log_capacity < 2) {
    return absl::InvalidArgumentError(absl::StrCat(who, "edge_log_capacity ", edge_log_capacity, " is below 2"));
  }
  return absl::OkStatus();
}

absl::StatusOr<GpiodDriverOptions> GpiodDriverOptionsFromRig(const v1::LightNodeConfig& config, double slot_rate_hz) {
  if (!config.has_gpiod()) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", config.id(), "\": no gpiod settings"));
  }
  const v1::GpiodLightSettings& g = config.gpiod();
  GpiodDriverOptions o;
  o.node_id = config.id();
  o.channel_count = config.channel_count();
  o.lines_per_channel = g.has_lines_per_channel() ? g.lines_per_channel() : 1;
  o.lines.chip = g.chip();
  o.lines.outputs.assign(g.channel_lines().begin(), g.channel_lines().end());
  if (g.has_slot_clock_line()) o.lines.slot_clock_line = g.slot_clock_line();
  o.lines.drives_slot_clock = g.drives_slot_clock();
  o.lines.consumer = absl::StrCat("fastage-", config.id());
  o.slot_rate_hz = slot_rate_hz;
  if (absl::Status s = o.Validate(); !s.ok()) return s;
  return o;
}

std::vector<uint8_t> RowLineValues(const ChannelLevels& levels, uint32_t lines_per_channel) {
  const uint32_t k = lines_per_channel;
  const uint32_t max_code = (1u << k) - 1;
  std::vector<uint8_t> values(levels.size() * k);
  for (size_t c = 0; c < levels.size(); ++c) {
    const uint32_t code = static_cast<uint32_t>(std::lround(levels[c] * static_cast<double>(max_code) / 65535.0));
    for (uint32_t j = 0; j < k; ++j) values[c * k + j] = static_cast<uint8_t>((code >> (k - 1 - j)) & 1u);
  }
  return values;
}

GpiodLightDriver::GpiodLightDriver(GpiodDriverOptions options, std::unique_ptr<GpioLines> lines)
    : options_(std::move(options)), lines_(std::move(lines)) {
  state_.channel_count = options_.channel_count;
}

absl::StatusOr<std::unique_ptr<GpiodLightDriver>> GpiodLightDriver::Open(GpiodDriverOptions options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  auto lines = OpenGpiodLines(options.lines);
  if (!lines.ok()) {
    return absl::Status(lines.status().code(),
                        absl::StrCat("light node \"", options.node_id, "\": ", lines.status().message()));
  }
  return Create(std::move(options), *std::move(lines));
}

absl::StatusOr<std::unique_ptr<GpiodLightDriver>> GpiodLightDriver::Create(GpiodDriverOptions options,
                                                                           std::unique_ptr<GpioLines> lines) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  if (lines == nullptr) return absl::InvalidArgumentError("no GPIO lines");
  std::unique_ptr<GpiodLightDriver> d(new GpiodLightDriver(std::move(options), std::move(lines)));
  if (absl::Status s = d->AllLow(); !s.ok()) return s;
  if (d->options_.run_edge_thread && !d->options_.lines.drives_slot_clock) {
    d->edge_thread_ = std::thread([raw = d.get()] { raw->InputLoop(); });
  }
  if (d->options_.lines.drives_slot_clock) {
    constexpr int64_t kSecond = 1'000'000'000;
    d->epoch_ns_ = timing::HostClockNs(/*realtime_clock=*/true) / kSecond * kSecond;
    d->slot_clock_ = std::make_unique<GpiodSlotClock>(d.get());
  }
  Logger("light.gpiod")
      ->info("{}: {} ({} channels x {} lines){}", d->Who(), d->lines_->Describe(), d->options_.channel_count,
             d->options_.lines_per_channel,
             d->options_.lines.drives_slot_clock
                 ? absl::StrFormat("; generates the slot clock at %g Hz in the runs the controller plans",
                                   d->options_.slot_rate_hz)
                 : std::string());
  return d;
}

GpiodLightDriver::~GpiodLightDriver() {
  stopping_.store(true);
  StopGenerator();
  if (edge_thread_.joinable()) edge_thread_.join();
  std::lock_guard<std::mutex> lock(mutex_);
  if (absl::Status s = AllLow(); !s.ok()) Logger("light.gpiod")->error("{}: {}", Who(), s.message());
}

std::string GpiodLightDriver::Who() const {
  return absl::StrCat("light node \"", options_.node_id, "\" (", options_.lines.chip, ")");
}

absl::Status GpiodLightDriver::AllLow() {
  absl::Status s = lines_->SetOutputs(std::vector<uint8_t>(options_.lines.outputs.size(), 0));
  if (!s.ok()) return absl::UnavailableError(absl::StrCat(Who(), ": setting the outputs low failed: ", s.message()));
  return s;
}

absl::Status GpiodLightDriver::StartGenerator(int64_t first, int64_t count) {
  // With mutex_ held. Edges at epoch + slot / rate on CLOCK_REALTIME, the clock every host shares through PTP.
  timing::SlotClockOptions clock;
  clock.slot_rate_hz = static_cast<uint32_t>(std::llround(options_.slot_rate_hz));
  clock.t0_ns = epoch_ns_;
  clock.first_slot = first;
  clock.slot_count = count;
  clock.realtime_clock = true;
  auto created = timing::SlotClock::Create(clock);
  if (!created.ok()) return created.status();
  generator_ = *std::move(created);
  generator_->AddListener([this](const timing::SlotEdge& edge) { OnGeneratedEdge(edge); });
  generator_->AddEndListener([this, end = first + count](int64_t missed) { OnGeneratedRunEnd(end, missed); });
  return generator_->Start();
}

int64_t GpiodLightDriver::SlotNow() const {
  const double since = static_cast<double>(timing::HostClockNs(/*realtime_clock=*/true) - epoch_ns_);
  return static_cast<int64_t>(std::floor(since * options_.slot_rate_hz / 1e9));
}

int64_t GpiodLightDriver::EdgeNs(int64_t slot) const {
  return epoch_ns_ + std::llround(static_cast<double>(slot) * 1e9 / options_.slot_rate_hz);
}

v1::SlotClockRun GpiodLightDriver::RunNow() const {
  v1::SlotClockRun run;
  run.set_first_slot(run_first_);
  run.set_end_slot(run_end_);
  run.set_first_edge_ns(EdgeNs(run_first_));
  run.set_current_slot(run_current_);
  return run;
}

absl::StatusOr<v1::SlotClockRun> GpiodLightDriver::RunClock(const v1::SlotClockRunRequest& request) {
  if (request.slots() <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": a clock run of ", request.slots(), " slots"));
  }
  const int64_t align = std::max<int64_t>(1, request.align_slots());
  int64_t first;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const int64_t now = SlotNow();
    if (request.first_slot() > 0 && !request.plan_only()) {
      first = request.first_slot();
      // Asked again for the run it started (a caller whose first answer did not reach it): done already.
      if (first == run_first_ && first + request.slots() == run_end_) return RunNow();
      if (first <= now) {
        return absl::FailedPreconditionError(
            absl::StrCat(Who(), ": a run from slot ", first, " would start in the past; plan it with more lead"));
      }
    } else {
      first = std::max({now + std::max<int64_t>(1, request.lead_slots()), run_end_, request.min_first_slot()});
      first = (first + align - 1) / align * align;
      if (request.plan_only()) {
        v1::SlotClockRun plan;
        plan.set_first_slot(first);
        plan.set_end_slot(first + request.slots());
        plan.set_first_edge_ns(EdgeNs(first));
        plan.set_current_slot(-1);
        return plan;
      }
    }
    if (run_first_ >= 0 && first < run_end_ && run_current_ < run_end_ - 1) {
      return absl::FailedPreconditionError(absl::StrCat(Who(), ": a run from slot ", first, " overlaps the last run [",
                                                        run_first_, ", ", run_end_, ")"));
    }
  }
  StopGenerator();  // the last run's thread, past its end
  std::lock_guard<std::mutex> lock(mutex_);
  run_first_ = first;
  run_end_ = first + request.slots();
  run_current_ = first - 1;
  if (absl::Status s = StartGenerator(first, request.slots()); !s.ok()) {
    run_end_ = first;  // nothing of it will come
    return absl::Status(s.code(), absl::StrCat(Who(), ": the slot clock did not start: ", s.message()));
  }
  return RunNow();
}

absl::StatusOr<v1::SlotClockRun> GpiodLightDriver::EndClock(int64_t align_slots) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (run_first_ < 0) return absl::FailedPreconditionError(absl::StrCat(Who(), ": the clock has had no run"));
  const int64_t current = std::max(run_current_, SlotNow());
  if (current >= run_end_ - 1) {
    return absl::FailedPreconditionError(
        absl::StrCat(Who(), ": the clock run [", run_first_, ", ", run_end_, ") is over"));
  }
  // The next edge may be on its way out; the one after it is the earliest safe end.
  const int64_t align = std::max<int64_t>(1, align_slots);
  const int64_t after = std::max(run_first_, current + 1);
  run_end_ = std::min(run_end_, run_first_ + (after - run_first_ + align - 1) / align * align);
  return RunNow();
}

absl::StatusOr<v1::SlotClockRun> GpiodLightDriver::ClockRun() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (run_first_ < 0) return absl::FailedPreconditionError(absl::StrCat(Who(), ": the clock has had no run"));
  return RunNow();
}

void GpiodLightDriver::StopGenerator() {
  // Without mutex_ held: the generator's listener takes it, and Stop() waits for the listener.
  std::unique_ptr<timing::SlotClock> generator;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    generator = std::move(generator_);
  }
  if (generator != nullptr) generator->Stop();
}

void GpiodLightDriver::InputLoop() {
  while (!stopping_.load()) {
    auto edges = lines_->WaitEdges(std::chrono::milliseconds(50));
    if (!edges.ok()) {
      {
        std::lock_guard<std::mutex> lock(mutex_);
        NoteFault("slot clock input", absl::StrCat(": ", edges.status().message()));
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      continue;
    }
    for (int64_t t : *edges) OnEdge(t);
  }
}

void GpiodLightDriver::OnGeneratedEdge(const timing::SlotEdge& edge) {
  {
    // A run ended early (a pause, an abort) puts out no edge from its new end on. The run's slots the generator
    // skipped on its way past the end were lost all the same.
    std::lock_guard<std::mutex> lock(mutex_);
    if (edge.slot >= run_end_) {
      PassedRunEndLocked(edge.slot, edge.missed_before);
      return;
    }
  }
  // Slots the generator reached a whole slot late or more were not produced (SlotClock goes on with the current
  // slot): OnEdge counts them as lost and steps over them.
  absl::Status s = lines_->SetClock(true);
  const int64_t rose = timing::HostClockNs(false);
  if (s.ok()) {
    OnEdge(rose, static_cast<uint64_t>(edge.missed_before));
  } else {
    std::lock_guard<std::mutex> lock(mutex_);
    NoteFault("slot clock output", absl::StrCat(": ", s.message()));
  }
  // Low again after clock_duty (at most half) of the slot: the listener returns before the next edge is due.
  timing::SleepUntilHostNs(edge.scheduled_ns + std::llround(1e9 / options_.slot_rate_hz * options_.clock_duty),
                           /*realtime_clock=*/true);
  (void)lines_->SetClock(false);
  // The slot's pulse is out (or was tried, and its fault noted).
  std::lock_guard<std::mutex> lock(mutex_);
  run_current_ = std::max(run_current_, edge.slot);
}

void GpiodLightDriver::NoteFault(const std::string& kind, const std::string& detail) {
  // Once per kind, as the take's record keeps it: an error text that changes from edge to edge is one fault.
  const bool known = std::any_of(state_.faults.begin(), state_.faults.end(),
                                 [&](const std::string& f) { return f.compare(0, kind.size(), kind) == 0; });
  if (!known) {
    state_.faults.push_back(kind + detail);
    Logger("light.gpiod")->warn("{}: {}{}", Who(), kind, detail);
  }
  RecordTakeFault(&state_.take_faults, kind, detail);
}

void GpiodLightDriver::OnGeneratedRunEnd(int64_t generator_end, int64_t missed_at_end) {
  std::lock_guard<std::mutex> lock(mutex_);
  PassedRunEndLocked(generator_end, missed_at_end);
}

void GpiodLightDriver::PassedRunEndLocked(int64_t slot, int64_t missed_before) {
  // The skipped slots [slot - missed_before, slot) that are the run's never went out: lost. The run is over.
  if (run_current_ >= run_end_ - 1) return;  // counted already
  const int64_t skipped = std::min(missed_before, run_end_ - (slot - missed_before));
  if (skipped > 0) CountLostLocked(static_cast<uint64_t>(skipped));
  run_current_ = run_end_ - 1;
}

void GpiodLightDriver::CountLostLocked(uint64_t lost) {
  if (state_.mode != DriverMode::kArmed || timing_.count == 0) return;
  timing_.lost_edges += lost;
  state_.steps += lost;
  NoteFault("slot clock: edges lost (LightStats.slot_clock.lost_edges counts them)");
}

void GpiodLightDriver::OnEdge(int64_t time_ns, std::optional<uint64_t> lost_before) {
  std::lock_guard<std::mutex> lock(mutex_);
  // Only edges of the take: one the kernel stamped before the arm (queued while idle) is not the take's first.
  if (state_.mode != DriverMode::kArmed || time_ns < armed_at_ns_) return;
  const double nominal = 1e9 / options_.slot_rate_hz;
  uint64_t lost = 0;
  if (timing_.count == 0) {
    // The generator's first run may have begun late: the slots it skipped before this edge are the take's, lost;
    // the mean period counts from when the first of them was due.
    lost = lost_before.value_or(0);
    first_edge_ns_ = time_ns - std::llround(static_cast<double>(lost) * nominal);
    if (lost > 0) {
      timing_.lost_edges += lost;
      NoteFault("slot clock: edges lost (LightStats.slot_clock.lost_edges counts them)");
    }
  } else {
    const double period = static_cast<double>(time_ns - last_edge_ns_);
    // Edges that never reached this node (the kernel's event queue of 16 overflowed, the line glitched), judged from
    // a gap of more than 1.5 periods; the generator says how many slots it did not produce (one it produced late is
    // not lost). The table steps over their slots, so it stays in phase with the clock.
    lost = lost_before              ? *lost_before
           : period > 1.5 * nominal ? static_cast<uint64_t>(std::llround(period / nominal)) - 1
                                    : 0;
    if (lost > 0) {
      timing_.lost_edges += lost;
      NoteFault("slot clock: edges lost (LightStats.slot_clock.lost_edges counts them)");
    } else {
      timing_.period_max_deviation_ns = std::max(timing_.period_max_deviation_ns, std::abs(period - nominal));
    }
    timing_.period_mean_ns =
        static_cast<double>(time_ns - first_edge_ns_) / static_cast<double>(timing_.count + timing_.lost_edges);
  }
  last_edge_ns_ = time_ns;
  if (timing_.count == 0) {
    // The line's numbering: its first edge since the arm by its time since the epoch, then one per edge.
    // Slots lost before it are numbered first.
    line_first_slot_ =
        std::llround(static_cast<double>(time_ns + RealtimeOffsetNs() - epoch_ns_) * options_.slot_rate_hz / 1e9) -
        static_cast<int64_t>(lost);
  }
  ++timing_.count;
  edges_.push_back(time_ns);
  if (edges_.size() > options_.edge_log_capacity) edges_.pop_front();
  if (start_at_mono_ns_ >= 0) {
    // A free-running clock: the table waits, dark, for its planned first edge; then the stepping starts there.
    if (start_at_mono_ns_ == kStartNotYet || time_ns < start_at_mono_ns_ - std::llround(nominal / 2)) return;
    start_at_mono_ns_ = -1;
    table_first_slot_ = LastSlot();
    table_first_edge_ns_ = time_ns;
    state_.steps = 0;
    lost = 0;
  }
  // The row is the slot's: the edges seen and lost since the arm, whether or not a write failed on the way.
  state_.steps += lost;
  const int row = static_cast<int>(state_.steps % row_lines_.size());
  ++state_.steps;
  state_.current_row = row;
  if (absl::Status s = lines_->SetOutputs(row_lines_[static_cast<size_t>(row)]); !s.ok()) {
    NoteFault("setting a row failed", absl::StrCat(": ", s.message()));
    return;
  }
  timing_.max_step_latency_ns = std::max(timing_.max_step_latency_ns, timing::HostClockNs(false) - time_ns);
}

DriverDescription GpiodLightDriver::Describe() const {
  DriverDescription d;
  d.backend = "gpiod";
  d.device = lines_->Describe();
  std::lock_guard<std::mutex> lock(mutex_);
  if (table_loaded_ && quantization_error_ > 0) {
    absl::StrAppend(&d.device, absl::StrFormat("; table rounded to %u bit(s) per channel, worst error %.1f %%",
                                               options_.lines_per_channel, 100 * quantization_error_));
  }
  d.channel_count = options_.channel_count;
  return d;
}

absl::Status GpiodLightDriver::LoadPatternTable(const PatternTable& table) {
  if (table.rows.empty()) return absl::InvalidArgumentError(absl::StrCat(Who(), ": the pattern table has no rows"));
  const uint32_t max_code = (1u << options_.lines_per_channel) - 1;
  std::vector<std::vector<uint8_t>> rows;
  double worst = 0;
  size_t worst_row = 0, worst_channel = 0;
  for (size_t r = 0; r < table.rows.size(); ++r) {
    const ChannelLevels& levels = table.rows[r];
    if (levels.size() != options_.channel_count) {
      return absl::InvalidArgumentError(
          absl::StrCat(Who(), ": row ", r, r < table.row_names.size() ? " (" + table.row_names[r] + ")" : "", " has ",
                       levels.size(), " levels; the node has ", options_.channel_count, " channels"));
    }
    for (size_t c = 0; c < levels.size(); ++c) {
      const double exact = levels[c] / 65535.0;
      const double error = std::abs(std::round(exact * max_code) / max_code - exact);
      if (error > worst) {
        worst = error;
        worst_row = r;
        worst_channel = c;
      }
    }
    rows.push_back(RowLineValues(levels, options_.lines_per_channel));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": a table loads only when idle"));
  }
  row_lines_ = std::move(rows);
  table_loaded_ = true;
  quantization_error_ = worst;
  if (worst > kQuantizationWarning) {
    Logger("light.gpiod")
        ->warn(
            "{}: the {}-row table rounds to {} line(s) per channel; worst error {:.1f} % of full scale at row {} "
            "({}) channel {}",
            Who(), table.rows.size(), options_.lines_per_channel, 100 * worst, worst_row,
            worst_row < table.row_names.size() ? table.row_names[worst_row] : "", worst_channel);
  }
  return absl::OkStatus();
}

int64_t GpiodLightDriver::RealtimeOffsetNs() {
  return timing::HostClockNs(/*realtime_clock=*/true) - timing::HostClockNs(/*realtime_clock=*/false);
}

int64_t GpiodLightDriver::LastSlot() const {
  return timing_.count == 0 ? -1 : line_first_slot_ + static_cast<int64_t>(timing_.count + timing_.lost_edges) - 1;
}

absl::Status GpiodLightDriver::StartAt(int64_t first_edge_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != DriverMode::kArmed) {
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": start a table only when armed"));
  }
  if (slot_clock_ != nullptr) {
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": it drives the slot clock; its runs start its table"));
  }
  if (first_edge_ns != kStartNotYet && first_edge_ns == start_requested_ns_) return absl::OkStatus();  // a retry
  const int64_t half = std::llround(5e8 / options_.slot_rate_hz);
  int64_t mono = kStartNotYet;
  if (first_edge_ns != kStartNotYet) {
    mono = first_edge_ns - RealtimeOffsetNs();
    if (timing_.count > 0 && last_edge_ns_ >= mono - half) {
      return absl::FailedPreconditionError(absl::StrCat(Who(), ": the edge at ", first_edge_ns,
                                                        " ns has passed (the clock is at slot ", LastSlot(), ")"));
    }
  }
  start_at_mono_ns_ = mono;
  start_requested_ns_ = first_edge_ns;
  table_first_slot_ = table_first_edge_ns_ = -1;
  state_.current_row = -1;
  state_.steps = 0;
  return AllLow();
}

absl::StatusOr<ClockInput> GpiodLightDriver::SlotClockInput() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != DriverMode::kArmed) {
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": it watches its slot-clock input only while armed"));
  }
  ClockInput in;
  const int64_t offset = RealtimeOffsetNs();
  in.last_slot = LastSlot();
  if (in.last_slot >= 0) {
    in.last_edge_ns = last_edge_ns_ + offset;
    const int64_t quiet = std::max<int64_t>(kQuietLineMinNs, std::llround(kQuietLinePeriods * 1e9 / options_.slot_rate_hz));
    in.running = timing::HostClockNs(false) - last_edge_ns_ < quiet;
  }
  in.table_first_slot = table_first_slot_;
  if (table_first_edge_ns_ >= 0) in.table_first_edge_ns = table_first_edge_ns_ + offset;
  return in;
}

absl::Status GpiodLightDriver::Arm() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != DriverMode::kIdle)
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": arm only when idle"));
  if (!table_loaded_) return absl::FailedPreconditionError(absl::StrCat(Who(), ": no pattern table loaded"));
  state_.mode = DriverMode::kArmed;
  state_.steps = 0;
  state_.current_row = -1;
  state_.take_faults.clear();
  state_.faults.clear();
  edges_.clear();
  timing_ = EdgeTiming{};
  start_at_mono_ns_ = -1;
  start_requested_ns_ = -1;
  table_first_slot_ = table_first_edge_ns_ = -1;
  armed_at_ns_ = timing::HostClockNs(false);
  return absl::OkStatus();
}

absl::Status GpiodLightDriver::Disarm() {
  StopGenerator();
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode == DriverMode::kArmed) state_.mode = DriverMode::kIdle;  // a blackout stays latched
  state_.current_row = -1;
  return AllLow();
}

absl::Status GpiodLightDriver::Blackout() {
  absl::Status s;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    state_.mode = DriverMode::kBlackout;
    state_.current_row = -1;
    s = AllLow();
  }
  StopGenerator();  // after the outputs are low: dark first
  return s;
}

absl::Status GpiodLightDriver::ResetBlackout() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != DriverMode::kBlackout) return absl::OkStatus();
  if (absl::Status s = AllLow(); !s.ok()) return s;
  state_.mode = DriverMode::kIdle;
  return absl::OkStatus();
}

DriverState GpiodLightDriver::State() const {
  std::lock_guard<std::mutex> lock(mutex_);
  DriverState state = state_;
  state.edges = timing_;
  return state;
}

double GpiodLightDriver::quantization_error() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return quantization_error_;
}

MeasuredEdges GpiodLightDriver::Edges() const {
  std::lock_guard<std::mutex> lock(mutex_);
  MeasuredEdges m;
  m.times_ns.assign(edges_.begin(), edges_.end());
  m.timing = timing_;
  return m;
}

}  // namespace stage::light
