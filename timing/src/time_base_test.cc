// TimeBase: exact slot times, no drift over any take length.
#include "stage/timing/time_base.h"

#include <cmath>

#include "gtest/gtest.h"

namespace stage::timing {
namespace {

TimeBase Base912() {
  auto base = TimeBase::Create(912);
  EXPECT_TRUE(base.ok());
  return *base;
}

TEST(TimeBaseTest, TicksAreTheLcmOfSlotRateAndNanoseconds) {
  TimeBase base = Base912();
  // lcm(912, 10^9) = 57 * 10^9: a slot is 62,500,000 ticks and a nanosecond 57.
  EXPECT_EQ(base.ticks_per_second(), 57'000'000'000);
  EXPECT_EQ(base.ticks_per_slot(), 62'500'000);
  EXPECT_EQ(base.ticks_per_ns(), 57);
  EXPECT_EQ(base.ticks_per_slot() * 912, base.ticks_per_second());
}

TEST(TimeBaseTest, SlotTenToTheSevenStartsAtExactlyTenToTheSevenOver912Seconds) {
  TimeBase base = Base912();
  const int64_t k = 10'000'000;
  const int64_t ticks = base.SlotStartTicks(k);
  // ticks / ticks_per_second == k / 912, exactly: cross-multiplied in integers.
  EXPECT_EQ(ticks * 912, k * base.ticks_per_second());
  // 10^7 / 912 s = 10964912280701.754... ns: the nanosecond value is the exact one rounded, not an accumulation.
  EXPECT_EQ(base.SlotStartNs(k), 10'964'912'280'702);
}

TEST(TimeBaseTest, NoCumulativeDriftOverTwentyFourHours) {
  TimeBase base = Base912();
  const int64_t slots_per_day = 912LL * 86400;
  // After exactly a day of slots the clock reads exactly a day.
  EXPECT_EQ(base.SlotStartNs(slots_per_day), 86'400'000'000'000);
  // Every slot of the day is within half a nanosecond of k * 10^9 / 912, checked on a sample spread over the day,
  // including the last slots.
  for (int64_t k = 0; k <= slots_per_day; k += 9973) {
    const long double exact = static_cast<long double>(k) * 1e9L / 912.0L;
    ASSERT_LE(std::fabs(static_cast<long double>(base.SlotStartNs(k)) - exact), 0.5L) << k;
  }
  // Periods in whole ns are 1096491 or 1096492; in every second exactly 208 of the 912 are the longer one
  // (912 * 1096491 = 999999792 ns), at the start of the day and at its end alike.
  for (int64_t first : {int64_t{0}, slots_per_day - 912}) {
    int longer = 0;
    for (int64_t k = first; k < first + 912; ++k) {
      const int64_t period = base.SlotStartNs(k + 1) - base.SlotStartNs(k);
      ASSERT_TRUE(period == 1'096'491 || period == 1'096'492) << k << ": " << period;
      longer += period == 1'096'492;
    }
    EXPECT_EQ(longer, 208) << "second starting at slot " << first;
  }
}

TEST(TimeBaseTest, SlotAtNsIsTheInverse) {
  TimeBase base = Base912();
  for (int64_t k : {0LL, 1LL, 37LL, 38LL, 123456LL, 78'796'800LL}) {
    // The exact edge of slot k lies within half a nanosecond of SlotStartNs(k).
    EXPECT_EQ(base.SlotAtNs(base.SlotStartNs(k) + 1), k) << k;
    EXPECT_EQ(base.SlotAtNs(base.SlotStartNs(k) - 1), k - 1) << k;
    EXPECT_EQ(base.SlotAtNs(base.SlotStartNs(k + 1) - 1), k) << k;
  }
  EXPECT_EQ(base.SlotAtNs(-1), -1);
}

TEST(TimeBaseTest, MicrosecondsResolveToNanoseconds) {
  TimeBase base = Base912();
  EXPECT_EQ(base.UsToTicks(20), 20'000 * 57);
  EXPECT_EQ(base.UsToTicks(0.0004), 0);
  EXPECT_EQ(base.UsToTicks(0.0006), 57);
  EXPECT_DOUBLE_EQ(base.TicksToUs(base.ticks_per_slot()), 1e6 / 912);
}

TEST(TimeBaseTest, TicksToUnitsRoundsEachEdgeToTheTimescale) {
  TimeBase base = Base912();
  // 1 ns units: slot 1 at 1096491.228 ns -> 1096491; slot 2 at 2192982.456 -> 2192982; slot 3 at 3289473.684.
  EXPECT_EQ(base.TicksToUnits(base.SlotStartTicks(1), 1'000'000), 1'096'491);
  EXPECT_EQ(base.TicksToUnits(base.SlotStartTicks(3), 1'000'000), 3'289'474);
  // 1 ps units.
  EXPECT_EQ(base.TicksToUnits(base.SlotStartTicks(1), 1'000), 1'096'491'228);
  // A day in picoseconds does not overflow.
  EXPECT_EQ(base.TicksToUnits(base.SlotStartTicks(912LL * 86400), 1'000), 86'400'000'000'000'000);
}

TEST(TimeBaseTest, FarSlotsAndTimesDoNotOverflow) {
  TimeBase base = Base912();
  EXPECT_EQ(base.max_slot(), INT64_MAX / 62'500'000);
  // Slot 10^12 (about 35 years) in ns, from the exact rational: 10^21 / 912 = 1096491228070175438.6 ns.
  EXPECT_EQ(base.SlotStartNs(1'000'000'000'000), 1'096'491'228'070'175'439);
  // A CLOCK_REALTIME nanosecond count today (2026) maps to its slot since the Unix epoch.
  const int64_t now_ns = 1'795'420'255'732'880'332;
  const int64_t k = base.SlotAtNs(now_ns);
  EXPECT_LE(base.SlotStartNs(k), now_ns);
  EXPECT_GT(base.SlotStartNs(k + 1), now_ns);
}

TEST(TimeBaseTest, RejectsImpossibleRates) {
  EXPECT_FALSE(TimeBase::Create(0).ok());
  EXPECT_FALSE(TimeBase::Create(2'000'000).ok());
  auto base = TimeBase::Create(1000);
  ASSERT_TRUE(base.ok());
  EXPECT_EQ(base->ticks_per_ns(), 1);
  EXPECT_EQ(base->ticks_per_slot(), 1'000'000);
}

}  // namespace
}  // namespace stage::timing
