// The external generator's arithmetic against a fake witness: where a run starts, what T0 it measures, where a pause
// ends it, and a line that goes quiet.
#include "external_sync_generator.h"

#include <mutex>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::controller {
namespace {

using ::testing::HasSubstr;

constexpr double kRate = 1000;  // 1 ms slots
constexpr int64_t kMs = 1'000'000;

// A line the test moves by hand: slot k's edge at k ms + `jitter_ns`, and the witness's table started where the
// test says.
class FakeWitness final : public ClockWitness {
 public:
  std::string Describe() const override { return "the fake witness"; }
  absl::StatusOr<v1::ClockInput> Read() override {
    std::lock_guard<std::mutex> lock(mu_);
    if (reads_until_running_ > 0) {
      --reads_until_running_;
      v1::ClockInput none;
      none.set_last_slot(-1);
      return none;
    }
    v1::ClockInput in;
    in.set_running(running_);
    in.set_last_slot(last_);
    in.set_last_edge_ns(last_ * kMs + jitter_ns_);
    in.set_table_first_slot(table_first_);
    in.set_table_first_edge_ns(table_first_ < 0 ? -1 : table_first_ * kMs + jitter_ns_);
    // Every read moves the line on by `step_` (a test's generator runs while the controller waits).
    last_ += step_;
    if (table_at_ >= 0 && last_ >= table_at_ && table_first_ < 0) table_first_ = table_at_;
    return in;
  }
  void Set(int64_t last, int64_t step, int64_t jitter_ns = 0) {
    std::lock_guard<std::mutex> lock(mu_);
    last_ = last;
    step_ = step;
    jitter_ns_ = jitter_ns;
  }
  void TableStartsAt(int64_t slot) {
    std::lock_guard<std::mutex> lock(mu_);
    table_at_ = slot;
  }
  void Stop() {
    std::lock_guard<std::mutex> lock(mu_);
    running_ = false;
    step_ = 0;
  }
  void NotRunningFor(int reads) {
    std::lock_guard<std::mutex> lock(mu_);
    reads_until_running_ = reads;
  }

 private:
  std::mutex mu_;
  bool running_ = true;
  int64_t last_ = 0, step_ = 0, jitter_ns_ = 0, table_at_ = -1, table_first_ = -1;
  int reads_until_running_ = 0;
};

struct Fixture {
  FakeWitness* witness = nullptr;
  std::unique_ptr<SyncGenerator> generator;
};

Fixture Make() {
  auto witness = std::make_unique<FakeWitness>();
  Fixture f;
  f.witness = witness.get();
  ExternalGeneratorOptions options;
  options.slot_rate_hz = kRate;
  options.end_margin_slots = 10;
  options.poll = std::chrono::milliseconds(1);
  auto made = NewExternalSyncGenerator(std::move(witness), options);
  EXPECT_TRUE(made.ok()) << made.status();
  f.generator = std::move(*made);
  return f;
}

std::chrono::steady_clock::time_point Soon() { return std::chrono::steady_clock::now() + std::chrono::seconds(30); }

TEST(ExternalSyncGeneratorTest, PlansALeadAheadAlignedAndTakesTheMeasuredEdgeAsT0) {
  Fixture f = Make();
  EXPECT_TRUE(f.generator->runs_free());
  f.witness->Set(/*last=*/1000, /*step=*/0, /*jitter_ns=*/0);
  SyncRunRequest request{/*slots=*/76, /*lead_slots=*/50, /*align_slots=*/38, /*min_first_slot=*/0,
                         /*first_of_take=*/true};
  auto planned = f.generator->Plan(request, Soon());
  ASSERT_TRUE(planned.ok()) << planned.status();
  // 1000 + 50 = 1050, aligned up to 38: 1064; T0 predicted from the last edge at the nominal rate.
  EXPECT_EQ(planned->first_slot, 1064);
  EXPECT_EQ(planned->end_slot, 1064 + 76);
  EXPECT_EQ(planned->first_edge_ns, 1064 * kMs);
  // The line runs on, and the witness's table starts on the planned edge, which it measured 700 ns late.
  f.witness->Set(1000, /*step=*/8, /*jitter_ns=*/700);
  f.witness->TableStartsAt(1064);
  auto started = f.generator->Start(request, *planned, Soon());
  ASSERT_TRUE(started.ok()) << started.status();
  EXPECT_EQ(started->first_slot, 1064);
  EXPECT_EQ(started->first_edge_ns, 1064 * kMs + 700);
  // Asked again, it is the same run.
  auto again = f.generator->Start(request, *planned, Soon());
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->first_edge_ns, started->first_edge_ns);
}

// The lights started a slot after the planned edge (T0 predicted late by more than half a slot): the take would be out
// of step with its cameras, so the run does not start, and the error says why.
TEST(ExternalSyncGeneratorTest, LightsThatStartedOffThePlannedEdgeFailTheStart) {
  Fixture f = Make();
  f.witness->Set(1000, 0);
  SyncRunRequest request{76, 50, 38, 0, /*first_of_take=*/true};
  auto planned = f.generator->Plan(request, Soon());
  ASSERT_TRUE(planned.ok());
  f.witness->Set(1000, 8);
  f.witness->TableStartsAt(1065);
  auto started = f.generator->Start(request, *planned, Soon());
  EXPECT_TRUE(absl::IsFailedPrecondition(started.status()));
  EXPECT_THAT(std::string(started.status().message()),
              HasSubstr("the lights started at slot 1065 of the external clock, not the planned 1064"));
}

TEST(ExternalSyncGeneratorTest, APauseEndsTheRunAtAFrameBoundaryPastTheMarginAndAResumeStartsAfterIt) {
  Fixture f = Make();
  f.witness->Set(0, 0);
  SyncRunRequest request{380, 10, 38, 0};
  auto planned = f.generator->Plan(request, Soon());
  ASSERT_TRUE(planned.ok());
  EXPECT_EQ(planned->first_slot, 38);
  f.witness->Set(40, 0);
  ASSERT_TRUE(f.generator->Start(request, *planned, Soon()).ok());
  f.witness->Set(100, 0);
  auto ended = f.generator->End(38);
  ASSERT_TRUE(ended.ok()) << ended.status();
  // The line is at 100; 10 slots of margin: the first frame boundary (38 + k x 38) at or after 111 is 114.
  EXPECT_EQ(ended->end_slot, 114);
  EXPECT_EQ(ended->current_slot, 100);
  // A resume: after the end, and no earlier than the gap's minimum.
  auto resumed = f.generator->Plan({228, 10, 38, 200}, Soon());
  ASSERT_TRUE(resumed.ok());
  EXPECT_EQ(resumed->first_slot, 228);
  // With the line past the run's end, there is nothing to end.
  f.witness->Set(120, 0);
  EXPECT_TRUE(absl::IsFailedPrecondition(f.generator->End(38).status()));
}

TEST(ExternalSyncGeneratorTest, ALineThatGoesQuietEndsTheRunWhereItStopped) {
  Fixture f = Make();
  f.witness->Set(0, 0);
  SyncRunRequest request{380, 10, 38, 0};
  auto planned = f.generator->Plan(request, Soon());
  ASSERT_TRUE(planned.ok());
  f.witness->Set(38, 0);
  ASSERT_TRUE(f.generator->Start(request, *planned, Soon()).ok());
  f.witness->Set(120, 0);
  auto run = f.generator->GetRun();
  ASSERT_TRUE(run.ok());
  EXPECT_EQ(run->current_slot, 120);
  EXPECT_EQ(run->end_slot, 38 + 380);
  f.witness->Stop();
  run = f.generator->GetRun();
  ASSERT_TRUE(run.ok());
  EXPECT_EQ(run->end_slot, 121);  // the run is over where the line went quiet
  EXPECT_EQ(run->current_slot, 120);
}

TEST(ExternalSyncGeneratorTest, WaitsForTheGeneratorToRunAndSaysWhatIsMissing) {
  Fixture f = Make();
  f.witness->NotRunningFor(5);
  f.witness->Set(500, 0);
  auto planned = f.generator->Plan({38, 10, 38, 0}, Soon());
  ASSERT_TRUE(planned.ok()) << planned.status();
  EXPECT_EQ(planned->first_slot, 532);

  Fixture quiet = Make();
  quiet.witness->NotRunningFor(1'000'000);
  auto refused = quiet.generator->Plan({38, 10, 38, 0}, std::chrono::steady_clock::now());
  EXPECT_TRUE(absl::IsFailedPrecondition(refused.status()));
  EXPECT_THAT(std::string(refused.status().message()),
              HasSubstr("the external generator's slot clock is not running on the input of the fake witness (no "
                        "edge seen): start the generator"));
}

TEST(ExternalSyncGeneratorTest, AGeneratorThatStopsBeforeTheFirstEdgeFailsTheStart) {
  Fixture f = Make();
  f.witness->Set(0, 0);
  SyncRunRequest request{38, 10, 38, 0};
  auto planned = f.generator->Plan(request, Soon());
  ASSERT_TRUE(planned.ok());
  f.witness->Set(20, 0);
  f.witness->Stop();
  auto started = f.generator->Start(request, *planned, Soon());
  EXPECT_TRUE(absl::IsUnavailable(started.status()));
  EXPECT_THAT(std::string(started.status().message()), HasSubstr("stopped at slot 20, before the run's first slot 38"));
}

TEST(ExternalGeneratorOptionsTest, ValidateNamesTheField) {
  ExternalGeneratorOptions o;
  o.end_margin_slots = 0;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("end_margin_slots"));
  o = ExternalGeneratorOptions();
  o.slot_rate_hz = 0;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("slot_rate_hz"));
}

}  // namespace
}  // namespace stage::controller
