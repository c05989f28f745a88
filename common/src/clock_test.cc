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
  std::atomic<bool> stop{false};
  std::thread sleeper([&] {
    clock.SleepUntilNs(1000, stop);
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
  std::atomic<bool> stop{false};
  EXPECT_TRUE(clock.SleepUntilNs(10, stop));
  EXPECT_EQ(clock.sleepers(), 0);
  stop = true;
  EXPECT_FALSE(clock.SleepUntilNs(10, stop));  // a set flag wins, even for a time that has passed
}

TEST(SimClockTest, InterruptWakesOnlySleepersWhoseFlagIsSet) {
  SimClock clock(0);
  std::atomic<bool> stop_a{false};
  std::atomic<bool> stop_b{false};
  std::atomic<int> result_a{-1};
  std::atomic<int> result_b{-1};
  std::thread a([&] { result_a = clock.SleepUntilNs(1'000'000, stop_a) ? 1 : 0; });
  std::thread b([&] { result_b = clock.SleepUntilNs(1'000'000, stop_b) ? 1 : 0; });
  WaitForSleepers(clock, 2);
  stop_a = true;
  clock.Interrupt();
  a.join();
  EXPECT_EQ(result_a.load(), 0);
  EXPECT_EQ(clock.NowNs(), 0);
  EXPECT_EQ(result_b.load(), -1);  // b's flag is clear: it sleeps on
  clock.AdvanceTo(1'000'000);
  b.join();
  EXPECT_EQ(result_b.load(), 1);
}

// A stop that lands before the sleeper reaches its sleep is never missed: one Interrupt() after setting the flag
// ends the sleep, however the two threads interleave. Repeated to give the interleavings a chance.
TEST(ClockTest, AStopSetBeforeTheSleepBeginsIsNeverMissed) {
  for (int round = 0; round < 200; ++round) {
    SimClock sim(0);
    RealClock real;
    for (Clock* clock : {static_cast<Clock*>(&sim), static_cast<Clock*>(&real)}) {
      std::atomic<bool> stop{false};
      std::atomic<int> result{-1};
      const int64_t far = clock->NowNs() + 600'000'000'000;
      std::thread sleeper([&] {
        if (round % 2 == 1) std::this_thread::yield();
        result = clock->SleepUntilNs(far, stop) ? 1 : 0;
      });
      stop = true;
      clock->Interrupt();
      sleeper.join();  // hangs for ten minutes if the wake-up was lost
      ASSERT_EQ(result.load(), 0) << "round " << round;
    }
  }
}

TEST(RealClockTest, SleepUntilReachesTheDeadline) {
  RealClock clock;
  int64_t start = clock.NowNs();
  std::atomic<bool> stop{false};
  EXPECT_TRUE(clock.SleepUntilNs(start + 2'000'000, stop));
  EXPECT_GE(clock.NowNs(), start + 2'000'000);
}

}  // namespace
}  // namespace stage
