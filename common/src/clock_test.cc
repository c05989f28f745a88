// Clocks: the simulated clock wakes sleepers exactly when time reaches them; the real clock moves forward.
#include "stage/common/clock.h"

#include <atomic>
#include <thread>

#include "gtest/gtest.h"

namespace stage {
namespace {

void WaitForSleepers(const SimClock& clock, int n) {
  while (clock.sleepers() != n) std::this_thread::yield();
}

TEST(SimClockTest, SleeperWakesOnlyWhenTimeIsReached) {
  SimClock clock(100);
  std::atomic<bool> woke{false};
  std::thread sleeper([&] {
    clock.SleepUntilNs(1000);
    woke = true;
  });
  WaitForSleepers(clock, 1);
  clock.AdvanceTo(999);
  // Still parked at 999 ns: the sleeper has not returned (it is counted as sleeping until it does).
  EXPECT_EQ(clock.sleepers(), 1);
  EXPECT_FALSE(woke.load());
  clock.Advance(1);
  sleeper.join();
  EXPECT_TRUE(woke.load());
  EXPECT_EQ(clock.NowNs(), 1000);
}

TEST(SimClockTest, NeverGoesBackwards) {
  SimClock clock(500);
  clock.AdvanceTo(100);
  EXPECT_EQ(clock.NowNs(), 500);
  clock.Advance(-5);
  EXPECT_EQ(clock.NowNs(), 500);
}

TEST(SimClockTest, PastDeadlineReturnsAtOnce) {
  SimClock clock(500);
  EXPECT_TRUE(clock.SleepUntilNs(10));
  EXPECT_EQ(clock.sleepers(), 0);
}

TEST(SimClockTest, InterruptWakesSleepersEarly) {
  SimClock clock(0);
  std::atomic<int> result{-1};
  std::thread sleeper([&] { result = clock.SleepUntilNs(1'000'000) ? 1 : 0; });
  WaitForSleepers(clock, 1);
  clock.Interrupt();
  sleeper.join();
  EXPECT_EQ(result.load(), 0);
  EXPECT_EQ(clock.NowNs(), 0);
}

TEST(RealClockTest, InterruptWakesSleepersEarly) {
  RealClock clock;
  std::atomic<int> result{-1};
  std::thread sleeper([&] { result = clock.SleepUntilNs(clock.NowNs() + 60'000'000'000) ? 1 : 0; });
  // Interrupt until the sleeper has gone: an interrupt before it starts sleeping would be missed.
  while (result.load() < 0) {
    clock.Interrupt();
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  sleeper.join();
  EXPECT_EQ(result.load(), 0);
}

TEST(RealClockTest, SleepUntilReachesTheDeadline) {
  RealClock clock;
  int64_t start = clock.NowNs();
  EXPECT_TRUE(clock.SleepUntilNs(start + 2'000'000));
  EXPECT_GE(clock.NowNs(), start + 2'000'000);
}

}  // namespace
}  // namespace stage
