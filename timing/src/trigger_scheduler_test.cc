// Scheduled triggers on the node: fired in time order at their time; missed when they arrive too late; late (not
// fired) when the node cannot fire them in time; nothing merged or dropped without a count.
#include "stage/timing/trigger_scheduler.h"

#include <algorithm>
#include <mutex>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::timing {
namespace {

using ::testing::ElementsAre;

constexpr int64_t kMs = 1'000'000;

struct Fired {
  std::mutex mutex;
  std::vector<std::pair<int64_t, int64_t>> slots_and_times;  // slot, when
  absl::Status operator()(int64_t slot) {
    std::lock_guard<std::mutex> lock(mutex);
    slots_and_times.push_back({slot, TriggerScheduler::NowNs()});
    return absl::OkStatus();
  }
};

TEST(TriggerSchedulerTest, FiresEachTriggerAtItsTimeInTimeOrder) {
  Fired fired;
  TriggerScheduler scheduler({.max_late_ns = 50 * kMs}, [&](int64_t s) { return fired(s); });
  const int64_t base = TriggerScheduler::NowNs() + 10 * kMs;
  // Submitted out of order.
  std::vector<int64_t> order = {5, 1, 9, 0, 3, 7, 2, 8, 6, 4};
  std::vector<int64_t> due(10);
  for (int64_t s : order) {
    due[s] = base + s * 2 * kMs;
    scheduler.Submit(s, due[s]);
  }
  scheduler.Drain();
  TriggerSchedulerStats stats = scheduler.stats();
  EXPECT_EQ(stats.received, 10u);
  EXPECT_EQ(stats.fired, 10u);
  EXPECT_EQ(stats.late + stats.missed, 0u);
  ASSERT_EQ(fired.slots_and_times.size(), 10u);
  for (int64_t s = 0; s < 10; ++s) {
    EXPECT_EQ(fired.slots_and_times[s].first, s);
    EXPECT_GE(fired.slots_and_times[s].second, due[s]) << "never early";
  }
  ASSERT_EQ(stats.leads_ns.size(), 10u);
  for (int64_t lead : stats.leads_ns) EXPECT_GT(lead, 0);
}

TEST(TriggerSchedulerTest, ATriggerThatArrivesTooLateIsMissedNotFired) {
  Fired fired;
  TriggerScheduler scheduler({.max_late_ns = 1 * kMs}, [&](int64_t s) { return fired(s); });
  const int64_t now = TriggerScheduler::NowNs();
  scheduler.Submit(41, now - 5 * kMs);  // 5 ms in the past, tolerance 1 ms
  scheduler.Submit(42, now + 5 * kMs);
  scheduler.Drain();
  TriggerSchedulerStats stats = scheduler.stats();
  EXPECT_EQ(stats.missed, 1u);
  EXPECT_THAT(stats.missed_slots, ElementsAre(41));
  // 42 arrived in time: fired, or late if a loaded machine woke the thread more than 1 ms after its time.
  EXPECT_EQ(stats.fired + stats.late, 1u);
  for (const auto& [slot, when] : fired.slots_and_times) EXPECT_EQ(slot, 42);
  ASSERT_EQ(stats.leads_ns.size(), 2u);
  EXPECT_LT(stats.leads_ns[0], -4 * kMs);  // the lead says how late it came
}

TEST(TriggerSchedulerTest, ATriggerTheNodeCannotFireInTimeIsLateNotFired) {
  std::vector<int64_t> fired_slots;
  int64_t stall_start = 0, stall_end = 0;
  TriggerScheduler scheduler({.max_late_ns = 1 * kMs}, [&](int64_t s) {
    fired_slots.push_back(s);
    // The first trigger fired holds the firing thread for 20 ms: those due meanwhile can no longer expose in time.
    if (stall_start == 0) {
      stall_start = TriggerScheduler::NowNs();
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      stall_end = TriggerScheduler::NowNs();
    }
    return absl::OkStatus();
  });
  const int64_t base = TriggerScheduler::NowNs() + 10 * kMs;
  std::vector<int64_t> due;
  for (int64_t s = 0; s < 12; ++s) {
    due.push_back(base + s * 3 * kMs);
    scheduler.Submit(s, due.back());
  }
  scheduler.Drain();
  TriggerSchedulerStats stats = scheduler.stats();
  EXPECT_EQ(stats.received, 12u);
  EXPECT_EQ(stats.fired + stats.late + stats.missed, 12u);
  EXPECT_EQ(stats.missed, 0u);
  ASSERT_GT(stall_end, 0);
  int due_in_stall = 0;
  for (int64_t s = 0; s < 12; ++s) {
    if (due[s] <= stall_start || due[s] + 1 * kMs >= stall_end) continue;
    ++due_in_stall;
    EXPECT_NE(std::find(stats.late_slots.begin(), stats.late_slots.end(), s), stats.late_slots.end()) << s;
    EXPECT_EQ(std::find(fired_slots.begin(), fired_slots.end(), s), fired_slots.end()) << "slot " << s << " fired";
  }
  EXPECT_GE(due_in_stall, 5);  // 20 ms with a trigger every 3 ms
  EXPECT_EQ(stats.fired, fired_slots.size());
}

TEST(TriggerSchedulerTest, ADeviceErrorCountsTheTriggerLate) {
  TriggerScheduler scheduler({.max_late_ns = 50 * kMs}, [](int64_t) { return absl::UnavailableError("camera gone"); });
  scheduler.Submit(3, TriggerScheduler::NowNs() + 2 * kMs);
  scheduler.Drain();
  EXPECT_EQ(scheduler.stats().late, 1u);
  EXPECT_THAT(scheduler.stats().late_slots, ElementsAre(3));
  EXPECT_EQ(scheduler.stats().fired, 0u);
}

TEST(TriggerSchedulerTest, StopCountsWhatWasNotFired) {
  Fired fired;
  TriggerScheduler scheduler({}, [&](int64_t s) { return fired(s); });
  const int64_t far = TriggerScheduler::NowNs() + 10'000 * kMs;
  scheduler.Submit(7, far);
  scheduler.Submit(8, far + kMs);
  scheduler.Stop();
  EXPECT_EQ(scheduler.stats().missed, 2u);
  EXPECT_THAT(scheduler.stats().missed_slots, ElementsAre(7, 8));
  EXPECT_TRUE(fired.slots_and_times.empty());
  scheduler.Submit(9, far);  // after Stop: counted, never fired
  EXPECT_EQ(scheduler.stats().missed, 3u);
}

}  // namespace
}  // namespace stage::timing
