// The gpiod backend's stepping logic on fake GPIO lines (no hardware): rows to line values, stepping on slot-clock
// edges, the edge record, the generator, blackout and faults. tests/gpiod_light_test.cc runs it on real lines.
#include "gpiod_light_driver.h"

#include <condition_variable>
#include <deque>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "light_node.h"
#include "stage/common/rig.h"
#include "stage/timing/slot_clock.h"

namespace stage::light {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

int64_t NowNs() { return timing::HostClockNs(false); }

// Edges of a take come after its arm: times from 1 ms after now.
int64_t After() { return NowNs() + 1'000'000; }
constexpr int64_t kPeriod = 1'096'491;

// Lines that remember what was written and hand out edges a test queues.
struct FakeLinesState {
  std::mutex mutex;
  std::condition_variable edge_ready;
  std::vector<std::vector<uint8_t>> writes;  // every SetOutputs, in order
  std::deque<int64_t> pending_edges;
  std::vector<std::pair<bool, int64_t>> clock;  // SetClock(level) with when
  bool fail_outputs = false;
  // The generator held at its first rising edge at or after stall_from_ns (CLOCK_MONOTONIC) until the test sets
  // release: the slots due meanwhile pass, as on a machine that did not run the generator's thread in time.
  int64_t stall_from_ns = -1;
  bool stalled = false;
  bool release = false;
  std::condition_variable stall_changed;
};

class FakeLines final : public GpioLines {
 public:
  explicit FakeLines(std::shared_ptr<FakeLinesState> s) : s_(std::move(s)) {}
  std::string Describe() const override { return "fake chip"; }
  absl::Status SetOutputs(const std::vector<uint8_t>& values) override {
    std::lock_guard<std::mutex> lock(s_->mutex);
    if (s_->fail_outputs) return absl::UnavailableError("line 3: Input/output error");
    s_->writes.push_back(values);
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<int64_t>> WaitEdges(std::chrono::nanoseconds timeout) override {
    std::unique_lock<std::mutex> lock(s_->mutex);
    s_->edge_ready.wait_for(lock, timeout, [&] { return !s_->pending_edges.empty(); });
    std::vector<int64_t> edges(s_->pending_edges.begin(), s_->pending_edges.end());
    s_->pending_edges.clear();
    return edges;
  }
  absl::Status SetClock(bool high) override {
    std::unique_lock<std::mutex> lock(s_->mutex);
    if (high && !s_->stalled && s_->stall_from_ns >= 0 && NowNs() >= s_->stall_from_ns) {
      s_->stalled = true;
      s_->stall_changed.notify_all();
      s_->stall_changed.wait(lock, [&] { return s_->release; });
    }
    s_->clock.emplace_back(high, NowNs());
    return absl::OkStatus();
  }

 private:
  std::shared_ptr<FakeLinesState> s_;
};

GpiodDriverOptions Options(uint32_t channels, uint32_t per_channel, bool thread, bool drives = false) {
  GpiodDriverOptions o;
  o.node_id = "lights-gpio-test";
  o.channel_count = channels;
  o.lines_per_channel = per_channel;
  o.lines.chip = "fake";
  for (uint32_t i = 0; i < channels * per_channel; ++i) o.lines.outputs.push_back(i);
  o.lines.slot_clock_line = channels * per_channel;
  o.lines.drives_slot_clock = drives;
  o.run_edge_thread = thread;
  return o;
}

struct Rig {
  std::shared_ptr<FakeLinesState> lines = std::make_shared<FakeLinesState>();
  std::unique_ptr<GpiodLightDriver> driver;
};

Rig Make(const GpiodDriverOptions& options) {
  Rig r;
  auto d = GpiodLightDriver::Create(options, std::make_unique<FakeLines>(r.lines));
  EXPECT_TRUE(d.ok()) << d.status();
  if (d.ok()) r.driver = *std::move(d);
  return r;
}

std::vector<uint8_t> LastWrite(Rig& r) {
  std::lock_guard<std::mutex> lock(r.lines->mutex);
  return r.lines->writes.empty() ? std::vector<uint8_t>{} : r.lines->writes.back();
}

PatternTable ThreeRows() {
  PatternTable t;
  t.pattern_set = "test";
  t.row_names = {"a", "b", "c"};
  t.rows = {{65535, 0}, {0, 21845}, {43690, 65535}};  // 2-bit codes: (3,0) (0,1) (2,3)
  return t;
}

TEST(GpiodLightDriverTest, RowsBecomeBinaryWeightedLineValues) {
  EXPECT_THAT(RowLineValues({0, 32767, 32768, 65535}, 1), ElementsAre(0, 0, 1, 1));
  // 4 lines: 0x8000 rounds to code 8 (1000), 0x1111 to 1 (0001), full scale to 15 (1111).
  EXPECT_THAT(RowLineValues({0x8000, 0x1111, 65535}, 4), ElementsAre(1, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1));
}

TEST(GpiodLightDriverTest, StepsThroughTheTableOnEdgesAndRecordsThem) {
  Rig r = Make(Options(2, 2, /*thread=*/false));
  ASSERT_NE(r.driver, nullptr);
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 0)) << "outputs start low";
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  r.driver->OnEdge(NowNs());  // not armed: no step, not recorded
  EXPECT_EQ(r.driver->State().steps, 0u);
  const int64_t before = NowNs();
  ASSERT_TRUE(r.driver->Arm().ok());
  r.driver->OnEdge(before);  // stamped before the arm (queued while idle): not the take's
  EXPECT_EQ(r.driver->State().steps, 0u);
  const int64_t period = static_cast<int64_t>(1e9 / 912);
  const int64_t t0 = After();
  const std::vector<std::vector<uint8_t>> expect = {{1, 1, 0, 0}, {0, 0, 0, 1}, {1, 0, 1, 1}};
  for (int i = 0; i < 7; ++i) {
    // One period 5 us late (edge 4): the record's jitter.
    r.driver->OnEdge(t0 + i * period + (i == 4 ? 5000 : 0));
    EXPECT_EQ(LastWrite(r), expect[static_cast<size_t>(i % 3)]) << "edge " << i;
    EXPECT_EQ(r.driver->State().current_row, i % 3);
  }
  DriverState state = r.driver->State();
  EXPECT_EQ(state.mode, DriverMode::kArmed);
  EXPECT_EQ(state.steps, 7u);
  ASSERT_TRUE(state.edges.has_value());
  EXPECT_EQ(state.edges->count, 7u);
  EXPECT_NEAR(state.edges->period_mean_ns, period, 1.0);
  EXPECT_NEAR(state.edges->period_max_deviation_ns, 5000, 1.0);
  MeasuredEdges m = r.driver->Edges();
  ASSERT_EQ(m.times_ns.size(), 7u);
  EXPECT_EQ(m.times_ns.front(), t0);
  EXPECT_EQ(m.times_ns[4], t0 + 4 * period + 5000);
  ASSERT_TRUE(r.driver->Disarm().ok());
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 0));
  r.driver->OnEdge(After());
  EXPECT_EQ(r.driver->State().steps, 7u) << "idle: edges do not step";
  // Arming again starts from the first row and a fresh record.
  ASSERT_TRUE(r.driver->Arm().ok());
  r.driver->OnEdge(After());
  EXPECT_EQ(LastWrite(r), expect[0]);
  EXPECT_EQ(r.driver->Edges().times_ns.size(), 1u);
}

TEST(GpiodLightDriverTest, SlotsTheGeneratorSkippedBeforeItsFirstEdgeAreLostAndStepped) {
  Rig r = Make(Options(2, 2, /*thread=*/false));
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  const int64_t t0 = After();
  r.driver->OnEdge(t0, /*lost_before=*/2);  // the run's first two slots passed before the generator woke
  EXPECT_EQ(r.driver->State().current_row, 2) << "the row of the run's third slot";
  EXPECT_THAT(LastWrite(r), ElementsAre(1, 0, 1, 1));
  r.driver->OnEdge(t0 + kPeriod, /*lost_before=*/0);
  EXPECT_EQ(r.driver->State().current_row, 0);
  const DriverState state = r.driver->State();
  ASSERT_TRUE(state.edges.has_value());
  EXPECT_EQ(state.edges->count, 2u);
  EXPECT_EQ(state.edges->lost_edges, 2u);
  EXPECT_EQ(state.steps, 4u);
  EXPECT_NEAR(state.edges->period_mean_ns, kPeriod, 2.0) << "from when the first lost slot was due";
  ASSERT_TRUE(r.driver->Disarm().ok());
}

// The witness of an external generator: a free-running clock on the input; the table waits, dark, for the edge the
// controller names, and the node reports the edges it numbered and the one its table started on (CLOCK_REALTIME).
TEST(GpiodLightDriverTest, OnAFreeRunningClockTheTableStartsAtThePlannedEdgeAndTheInputIsReported) {
  Rig r = Make(Options(2, 2, /*thread=*/false));
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  EXPECT_TRUE(absl::IsFailedPrecondition(r.driver->SlotClockInput().status())) << "idle: it does not watch";
  EXPECT_TRUE(absl::IsFailedPrecondition(r.driver->StartAt(0)));
  ASSERT_TRUE(r.driver->Arm().ok());
  ASSERT_TRUE(r.driver->StartAt(kStartNotYet).ok());
  const int64_t offset = timing::HostClockNs(true) - timing::HostClockNs(false);
  const int64_t t0 = After();
  for (int i = 0; i < 5; ++i) r.driver->OnEdge(t0 + i * kPeriod);
  EXPECT_EQ(r.driver->State().steps, 0u) << "waiting for its planned edge: no step";
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 0));
  auto in = r.driver->SlotClockInput();
  ASSERT_TRUE(in.ok()) << in.status();
  EXPECT_EQ(in->table_first_slot, -1);
  const int64_t first_number = in->last_slot - 4;
  EXPECT_NEAR(static_cast<double>(in->last_edge_ns), static_cast<double>(t0 + 4 * kPeriod + offset), 2e5);
  // An edge that has passed cannot be the first; the 8th edge (5 us early) can.
  EXPECT_TRUE(absl::IsFailedPrecondition(r.driver->StartAt(t0 + 2 * kPeriod + offset)));
  ASSERT_TRUE(r.driver->StartAt(t0 + 7 * kPeriod + offset).ok());
  r.driver->OnEdge(t0 + 5 * kPeriod);
  r.driver->OnEdge(t0 + 6 * kPeriod);
  EXPECT_EQ(r.driver->State().steps, 0u);
  r.driver->OnEdge(t0 + 7 * kPeriod - 5000);
  EXPECT_EQ(r.driver->State().current_row, 0);
  EXPECT_THAT(LastWrite(r), ElementsAre(1, 1, 0, 0));
  r.driver->OnEdge(t0 + 8 * kPeriod);
  EXPECT_EQ(r.driver->State().current_row, 1);
  in = r.driver->SlotClockInput();
  ASSERT_TRUE(in.ok());
  EXPECT_EQ(in->table_first_slot, first_number + 7);
  EXPECT_EQ(in->last_slot, first_number + 8);
  EXPECT_NEAR(static_cast<double>(in->table_first_edge_ns), static_cast<double>(t0 + 7 * kPeriod - 5000 + offset),
              2e5);
  // The edges are in the future (After()), so the line counts as running.
  EXPECT_TRUE(in->running);
}

TEST(GpiodLightDriverTest, TheEdgeRecordKeepsTheLastEdgesAndCountsAll) {
  GpiodDriverOptions o = Options(1, 1, false);
  o.edge_log_capacity = 4;
  Rig r = Make(o);
  ASSERT_TRUE(r.driver->LoadPatternTable({"t", {"x"}, {{65535}}}).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  const int64_t t0 = After();
  for (int i = 0; i < 10; ++i) r.driver->OnEdge(t0 + i * 1000);
  MeasuredEdges m = r.driver->Edges();
  EXPECT_THAT(m.times_ns, ElementsAre(t0 + 6000, t0 + 7000, t0 + 8000, t0 + 9000));
  EXPECT_EQ(m.timing.count, 10u);
  EXPECT_NEAR(m.timing.period_mean_ns, 1000, 1e-9);
}

TEST(GpiodLightDriverTest, BlackoutIsDarkAndLatched) {
  Rig r = Make(Options(2, 2, false));
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  r.driver->OnEdge(After());
  EXPECT_THAT(LastWrite(r), ElementsAre(1, 1, 0, 0));
  ASSERT_TRUE(r.driver->Blackout().ok());
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 0));
  r.driver->OnEdge(After());
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 0)) << "no edge lights a node in blackout";
  EXPECT_EQ(r.driver->State().mode, DriverMode::kBlackout);
  EXPECT_TRUE(absl::IsFailedPrecondition(r.driver->Arm()));
  EXPECT_TRUE(r.driver->Disarm().ok());
  EXPECT_EQ(r.driver->State().mode, DriverMode::kBlackout) << "disarm does not clear the latch";
  ASSERT_TRUE(r.driver->ResetBlackout().ok());
  EXPECT_EQ(r.driver->State().mode, DriverMode::kIdle);
  EXPECT_TRUE(r.driver->Arm().ok());
}

TEST(GpiodLightDriverTest, BadTablesAndBadOptionsAreRefusedByName) {
  Rig r = Make(Options(2, 1, false));
  PatternTable t = ThreeRows();
  t.rows[1].push_back(7);
  absl::Status s = r.driver->LoadPatternTable(t);
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_THAT(std::string(s.message()), HasSubstr("row 1 (b) has 3 levels; the node has 2 channels"));
  EXPECT_TRUE(absl::IsFailedPrecondition(r.driver->Arm())) << "no table loaded";
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  EXPECT_TRUE(absl::IsFailedPrecondition(r.driver->LoadPatternTable(ThreeRows()))) << "armed";

  GpiodDriverOptions o = Options(2, 1, false);
  o.lines.outputs = {0, 1, 1};
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("channel_lines has 3 lines"));
  o.lines.outputs = {0, 0};
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("line 0 is listed twice"));
  o.lines.outputs = {0, 1};
  o.lines.slot_clock_line = 1;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("slot_clock_line 1 is also a channel line"));
  o.lines.slot_clock_line.reset();
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("gpiod.slot_clock_line is required"));
}

TEST(GpiodLightDriverTest, RoundingOfTheTableIsReported) {
  Rig r = Make(Options(2, 1, false));
  ASSERT_TRUE(r.driver->LoadPatternTable({"t", {"half"}, {{16384, 65535}}}).ok());
  EXPECT_NEAR(r.driver->quantization_error(), 16384 / 65535.0, 1e-9);
  EXPECT_THAT(r.driver->Describe().device, HasSubstr("worst error 25.0 %"));
  Rig exact = Make(Options(2, 1, false));
  ASSERT_TRUE(exact.driver->LoadPatternTable({"t", {"on-off"}, {{0, 65535}}}).ok());
  EXPECT_EQ(exact.driver->quantization_error(), 0);
}

TEST(GpiodLightDriverTest, InputThreadStepsOnEveryQueuedEdge) {
  Rig r = Make(Options(2, 2, /*thread=*/true));
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  {
    // Five edges at once: a reader that fell behind gets them all and steps on each (the table stays in phase).
    std::lock_guard<std::mutex> lock(r.lines->mutex);
    const int64_t t0 = After();
    for (int i = 0; i < 5; ++i) r.lines->pending_edges.push_back(t0 + i * kPeriod);
    r.lines->edge_ready.notify_all();
  }
  for (int i = 0; i < 500 && r.driver->State().steps < 5; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  EXPECT_EQ(r.driver->State().steps, 5u);
  EXPECT_EQ(r.driver->State().current_row, 1);
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 1));
  EXPECT_EQ(r.driver->Edges().times_ns.size(), 5u);
}

// Waits (a test's bound only) until the driver's clock run has put out its last edge.
void WaitForRunEnd(GpiodLightDriver& driver) {
  for (int i = 0; i < 5000; ++i) {
    auto run = driver.ClockRun();
    if (run.ok() && run->current_slot() >= run->end_slot() - 1) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
}

TEST(GpiodLightDriverTest, GeneratorDrivesTheSlotClockInPlannedRunsAndStepsOnIt) {
  GpiodDriverOptions o = Options(1, 1, /*thread=*/true, /*drives=*/true);
  o.slot_rate_hz = 912;
  Rig r = Make(o);
  ASSERT_NE(r.driver->slot_clock(), nullptr);
  ASSERT_TRUE(r.driver->LoadPatternTable({"t", {"on", "off"}, {{65535}, {0}}}).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  EXPECT_THAT(r.driver->ClockRun().status().message(), HasSubstr("the clock has had no run"));
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  EXPECT_EQ(r.driver->Edges().timing.count, 0u) << "armed, the clock waits for a run";

  // Plan, then start exactly the planned run: its first slot a multiple of 38, T0 its edge on the epoch.
  v1::SlotClockRunRequest request;
  request.set_slots(250);
  request.set_lead_slots(200);  // planned first: room for a loaded machine between the plan and the start
  request.set_align_slots(38);
  request.set_plan_only(true);
  auto plan = r.driver->RunClock(request);
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_EQ(plan->first_slot() % 38, 0);
  EXPECT_EQ(plan->end_slot(), plan->first_slot() + 250);
  request.set_plan_only(false);
  request.set_first_slot(plan->first_slot());
  auto started = r.driver->RunClock(request);
  ASSERT_TRUE(started.ok()) << started.status();
  EXPECT_EQ(started->first_edge_ns(), plan->first_edge_ns());
  auto again = r.driver->RunClock(request);  // asked twice: started once
  ASSERT_TRUE(again.ok()) << again.status();
  WaitForRunEnd(*r.driver);
  auto run = r.driver->ClockRun();
  ASSERT_TRUE(run.ok());
  EXPECT_EQ(run->current_slot(), plan->end_slot() - 1);
  MeasuredEdges m = r.driver->Edges();
  // Every slot of the run went out, or was one the generator reached too late and skipped (counted as lost).
  EXPECT_EQ(m.timing.count + m.timing.lost_edges, 250u);
  EXPECT_EQ(r.driver->State().steps, m.timing.count + m.timing.lost_edges) << "one step per slot";
  {
    // One high and one low per edge, alternating, starting high and ending low.
    std::lock_guard<std::mutex> lock(r.lines->mutex);
    ASSERT_EQ(r.lines->clock.size(), 2 * m.timing.count);
    EXPECT_TRUE(r.lines->clock.front().first);
    EXPECT_FALSE(r.lines->clock.back().first);
    for (size_t i = 1; i < r.lines->clock.size(); ++i) {
      ASSERT_NE(r.lines->clock[i].first, r.lines->clock[i - 1].first) << "clock write " << i;
    }
  }
  // Edges come at t0 + k / rate (absolute, no drift): from the first recorded edge to the last is a whole number of
  // periods, counting slots the generator had to skip, give or take the scheduling delay of two wake-ups.
  const double period = 1e9 / 912;
  const double span = static_cast<double>(m.times_ns.back() - m.times_ns.front());
  const double slots = static_cast<double>(m.timing.count - 1 + m.timing.lost_edges);
  EXPECT_NEAR(span, slots * period, 20e6) << "over " << m.timing.count << " edges";

  // A run in the past, or one overlapping the last, is refused.
  request.set_first_slot(plan->first_slot() - 38);
  EXPECT_THAT(r.driver->RunClock(request).status().message(), HasSubstr("would start in the past"));
  ASSERT_TRUE(r.driver->Disarm().ok());
}

// When slot `slot` of `run` is due, on CLOCK_MONOTONIC (the fake lines' clock), less half a period.
int64_t MonotonicDue(const v1::SlotClockRun& run, int64_t slot) {
  const int64_t offset = timing::HostClockNs(/*realtime_clock=*/true) - timing::HostClockNs(/*realtime_clock=*/false);
  return run.first_edge_ns() - offset + (slot - run.first_slot()) * kPeriod - kPeriod / 2;
}

// Waits until the generator is held (true) or the driver's run is over (false: a machine so loaded that the
// generator passed the stall's time without an edge); once held, keeps it so until the edge at `until_edge_ns`
// (CLOCK_REALTIME) and two periods more have passed. The generator is let go either way.
bool HoldUntil(Rig& r, int64_t until_edge_ns) {
  bool held = false;
  for (int i = 0; i < 60000 && !held; ++i) {
    {
      std::unique_lock<std::mutex> lock(r.lines->mutex);
      held = r.lines->stall_changed.wait_for(lock, std::chrono::milliseconds(1), [&] { return r.lines->stalled; });
    }
    auto run = r.driver->ClockRun();
    if (!held && run.ok() && run->current_slot() >= run->end_slot() - 1) break;
  }
  while (held && timing::HostClockNs(/*realtime_clock=*/true) < until_edge_ns + 2 * kPeriod) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  std::lock_guard<std::mutex> lock(r.lines->mutex);
  r.lines->release = true;
  r.lines->stall_changed.notify_all();
  return held;
}

// A 38-slot run whose generator is held at the edge of slot `stall_slot` (or the first it puts out after it) past
// later slots: every slot of the run is sent or counted lost, the table steps once per slot (so it stays in phase), and
// the run ends.
void ExpectStalledRunAccounted(int64_t stall_slot, int64_t stall_slots) {
  GpiodDriverOptions o = Options(1, 1, /*thread=*/true, /*drives=*/true);
  o.slot_rate_hz = 912;
  Rig r = Make(o);
  ASSERT_TRUE(r.driver->LoadPatternTable({"t", {"on", "off"}, {{65535}, {0}}}).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  v1::SlotClockRunRequest request;
  request.set_slots(38);
  request.set_lead_slots(200);  // planned first: room for a loaded machine between the plan and the start
  request.set_plan_only(true);
  auto plan = r.driver->RunClock(request);
  ASSERT_TRUE(plan.ok()) << plan.status();
  r.lines->stall_from_ns = MonotonicDue(*plan, plan->first_slot() + stall_slot);
  request.set_plan_only(false);
  request.set_first_slot(plan->first_slot());
  auto run = r.driver->RunClock(request);
  ASSERT_TRUE(run.ok()) << run.status();
  const bool held = HoldUntil(r, run->first_edge_ns() + (stall_slot + stall_slots) * kPeriod);
  WaitForRunEnd(*r.driver);
  auto ended = r.driver->ClockRun();
  ASSERT_TRUE(ended.ok());
  EXPECT_EQ(ended->current_slot(), run->end_slot() - 1) << "the run is over";
  const MeasuredEdges m = r.driver->Edges();
  EXPECT_EQ(m.timing.count + m.timing.lost_edges, 38u) << (held ? "held" : "never held: the machine was too slow");
  EXPECT_EQ(r.driver->State().steps, 38u) << "one step per slot, lost or not";
  ASSERT_TRUE(r.driver->Disarm().ok());
}

TEST(GpiodLightDriverTest, SlotsSkippedAfterTheFirstEdgeAreCountedLost) { ExpectStalledRunAccounted(0, 5); }

TEST(GpiodLightDriverTest, SlotsSkippedAtTheRunsEndAreCountedLostAndTheRunEnds) { ExpectStalledRunAccounted(35, 4); }

TEST(GpiodLightDriverTest, SlotsSkippedPastAnEarlyEndAreCountedLostAndTheRunEnds) {
  GpiodDriverOptions o = Options(1, 1, /*thread=*/true, /*drives=*/true);
  o.slot_rate_hz = 912;
  Rig r = Make(o);
  ASSERT_TRUE(r.driver->LoadPatternTable({"t", {"on", "off"}, {{65535}, {0}}}).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  v1::SlotClockRunRequest request;
  request.set_slots(1'000'000);
  request.set_lead_slots(200);  // planned first: room for a loaded machine between the plan and the start
  request.set_align_slots(38);
  request.set_plan_only(true);
  auto plan = r.driver->RunClock(request);
  ASSERT_TRUE(plan.ok()) << plan.status();
  r.lines->stall_from_ns = MonotonicDue(*plan, plan->first_slot() + 10);
  request.set_plan_only(false);
  request.set_first_slot(plan->first_slot());
  auto run = r.driver->RunClock(request);
  ASSERT_TRUE(run.ok()) << run.status();
  {
    // The run is far longer than the test: the generator puts out an edge after the stall's time sooner or later.
    std::unique_lock<std::mutex> lock(r.lines->mutex);
    ASSERT_TRUE(r.lines->stall_changed.wait_for(lock, std::chrono::seconds(60), [&] { return r.lines->stalled; }));
  }
  // Ended while the generator is held: it comes back past the new end.
  auto ended = r.driver->EndClock(38);
  ASSERT_TRUE(ended.ok()) << ended.status();
  EXPECT_TRUE(HoldUntil(r, run->first_edge_ns() + (ended->end_slot() - run->first_slot()) * kPeriod));
  WaitForRunEnd(*r.driver);
  auto after = r.driver->ClockRun();
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->current_slot(), ended->end_slot() - 1) << "the run is over";
  const MeasuredEdges m = r.driver->Edges();
  EXPECT_EQ(m.timing.count + m.timing.lost_edges, static_cast<uint64_t>(ended->end_slot() - ended->first_slot()));
  ASSERT_TRUE(r.driver->Disarm().ok());
}

TEST(GpiodLightDriverTest, AClockRunEndedEarlyStopsAtAFrameBoundary) {
  GpiodDriverOptions o = Options(1, 1, /*thread=*/true, /*drives=*/true);
  o.slot_rate_hz = 912;
  Rig r = Make(o);
  ASSERT_TRUE(r.driver->LoadPatternTable({"t", {"on", "off"}, {{65535}, {0}}}).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  v1::SlotClockRunRequest request;
  request.set_slots(1'000'000);  // far longer than the test
  request.set_lead_slots(5);
  request.set_align_slots(38);
  auto run = r.driver->RunClock(request);
  ASSERT_TRUE(run.ok()) << run.status();
  for (int i = 0; i < 5000 && r.driver->Edges().timing.count < 10; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  auto ended = r.driver->EndClock(38);
  ASSERT_TRUE(ended.ok()) << ended.status();
  EXPECT_EQ((ended->end_slot() - ended->first_slot()) % 38, 0);
  EXPECT_LT(ended->end_slot(), run->end_slot());
  WaitForRunEnd(*r.driver);
  std::this_thread::sleep_for(std::chrono::milliseconds(50));  // any edge past the end would have come by now
  const MeasuredEdges m = r.driver->Edges();
  EXPECT_EQ(m.timing.count + m.timing.lost_edges, static_cast<uint64_t>(ended->end_slot() - ended->first_slot()));
  EXPECT_THAT(r.driver->EndClock(38).status().message(), HasSubstr("is over"));
  // The next run follows the last one.
  request.set_slots(38);
  auto next = r.driver->RunClock(request);
  ASSERT_TRUE(next.ok()) << next.status();
  EXPECT_GE(next->first_slot(), ended->end_slot());
  ASSERT_TRUE(r.driver->Disarm().ok());
}

TEST(GpiodLightDriverTest, AFailedOutputWriteIsAFaultAndABlackoutThatCannotConfirmSaysSo) {
  Rig r = Make(Options(2, 1, false));
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  const int64_t t0 = After();
  {
    std::lock_guard<std::mutex> lock(r.lines->mutex);
    r.lines->fail_outputs = true;
  }
  r.driver->OnEdge(t0);
  DriverState state = r.driver->State();
  ASSERT_EQ(state.faults.size(), 1u);
  EXPECT_THAT(state.faults[0], HasSubstr("setting a row failed: line 3: Input/output error"));
  ASSERT_EQ(state.take_faults.size(), 1u);
  // The next edge's row is the next slot's: a failed write does not put the table a slot behind.
  {
    std::lock_guard<std::mutex> lock(r.lines->mutex);
    r.lines->fail_outputs = false;
  }
  r.driver->OnEdge(t0 + kPeriod);
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0)) << "row 1 (b) rounds to off, off";
  EXPECT_EQ(r.driver->State().current_row, 1);
  {
    std::lock_guard<std::mutex> lock(r.lines->mutex);
    r.lines->fail_outputs = true;
  }
  absl::Status s = r.driver->Blackout();
  EXPECT_TRUE(absl::IsUnavailable(s));
  EXPECT_THAT(std::string(s.message()), HasSubstr("lights-gpio-test"));
  {
    std::lock_guard<std::mutex> lock(r.lines->mutex);
    r.lines->fail_outputs = false;
  }
  EXPECT_TRUE(r.driver->ResetBlackout().ok());
}

TEST(GpiodLightDriverTest, LostEdgesAreCountedAndSteppedOver) {
  Rig r = Make(Options(2, 2, false));
  ASSERT_TRUE(r.driver->LoadPatternTable(ThreeRows()).ok());
  ASSERT_TRUE(r.driver->Arm().ok());
  const int64_t t0 = After();
  r.driver->OnEdge(t0);
  r.driver->OnEdge(t0 + kPeriod);
  r.driver->OnEdge(t0 + 4 * kPeriod);  // the edges of slots 2 and 3 never came
  DriverState state = r.driver->State();
  EXPECT_EQ(state.steps, 5u);
  EXPECT_EQ(state.current_row, 4 % 3) << "the row of slot 4";
  EXPECT_THAT(LastWrite(r), ElementsAre(0, 0, 0, 1));
  ASSERT_TRUE(state.edges.has_value());
  EXPECT_EQ(state.edges->count, 3u);
  EXPECT_EQ(state.edges->lost_edges, 2u);
  EXPECT_NEAR(state.edges->period_mean_ns, kPeriod, 1.0);
  EXPECT_NEAR(state.edges->period_max_deviation_ns, std::abs(kPeriod - 1e9 / 912), 1.0) << "gaps are not jitter";
  ASSERT_EQ(state.take_faults.size(), 1u);
  EXPECT_THAT(state.take_faults[0], HasSubstr("slot clock: edges lost"));
}

TEST(GpiodLightDriverTest, ALightNodeOnGpioReportsTheMeasuredSlotClock) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  const v1::LightNodeConfig* config = nullptr;
  for (const auto& n : rig->rig.light_nodes()) {
    if (n.backend() == v1::LIGHT_BACKEND_GPIOD) config = &n;
  }
  ASSERT_NE(config, nullptr) << "the shipped rig has gpiod nodes";
  auto options = GpiodDriverOptionsFromRig(*config, 912);
  ASSERT_TRUE(options.ok()) << options.status();
  options->run_edge_thread = false;
  auto state = std::make_shared<FakeLinesState>();
  auto driver = GpiodLightDriver::Create(*options, std::make_unique<FakeLines>(state));
  ASSERT_TRUE(driver.ok()) << driver.status();
  GpiodLightDriver* raw = driver->get();
  auto node = LightNode::Create(*config, *std::move(driver), "h");
  ASSERT_TRUE(node.ok()) << node.status();
  v1::ArmLightRequest request;
  request.set_take_id("t");
  for (int r = 0; r < 38; ++r) {
    v1::PatternRow* row = request.mutable_table()->add_rows();
    row->set_name("p" + std::to_string(r));
    for (uint32_t c = 0; c < config->channel_count(); ++c) row->add_levels(r % 4 == 0 && c == 0 ? 65535 : 0);
  }
  request.set_heartbeat_timeout_ms(60'000);
  ASSERT_TRUE((*node)->Arm(request).ok());
  const int64_t t0 = After();
  for (int i = 0; i < 3; ++i) raw->OnEdge(t0 + i * kPeriod);
  v1::LightStats stats = (*node)->Stats();
  EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_ARMED);
  EXPECT_EQ(stats.slot_edges(), 3u);
  EXPECT_EQ(stats.slot_clock().edges(), 3u);
  EXPECT_NEAR(stats.slot_clock().period_mean_us(), 1096.491, 1e-3);
  EXPECT_EQ((*node)->Info().backend(), "gpiod");
}

}  // namespace
}  // namespace stage::light
