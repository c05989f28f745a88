// The slot-clock generator: exact edges in virtual time with no drift, every edge in lockstep, real-time edges never
// early and missed (not delivered late) when the thread falls a slot behind.
#include "stage/timing/slot_clock.h"

#include <chrono>
#include <mutex>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::timing {
namespace {

using ::testing::ElementsAre;

struct Recorder {
  std::mutex mutex;
  std::vector<SlotEdge> edges;
  void operator()(const SlotEdge& e) {
    std::lock_guard<std::mutex> lock(mutex);
    edges.push_back(e);
  }
  size_t size() {
    std::lock_guard<std::mutex> lock(mutex);
    return edges.size();
  }
};

// Advances `clock` to each edge in turn, waiting until the generator has delivered it.
void Step(SimClock& clock, Recorder& rec, const TimeBase& base, int64_t t0, int64_t first, int64_t count) {
  for (int64_t k = first; k < first + count; ++k) {
    clock.AdvanceTo(t0 + base.SlotStartNs(k));
    for (int i = 0; i < 10000 && rec.size() < static_cast<size_t>(k - first + 1); ++i) {
      std::this_thread::sleep_for(std::chrono::microseconds(50));
    }
    ASSERT_EQ(rec.size(), static_cast<size_t>(k - first + 1)) << "edge " << k << " not delivered";
  }
}

TEST(SlotClockTest, VirtualEdgesAreExact) {
  SimClock clock(0);
  const int64_t t0 = 5'000'000;
  auto gen = SlotClock::Create({.slot_rate_hz = 912, .t0_ns = t0, .first_slot = 0, .slot_count = 100}, &clock);
  ASSERT_TRUE(gen.ok()) << gen.status();
  Recorder rec;
  (*gen)->AddListener([&](const SlotEdge& e) { rec(e); });
  std::vector<int64_t> ends;
  (*gen)->AddEndListener([&](int64_t missed_at_end) { ends.push_back(missed_at_end); });
  ASSERT_TRUE((*gen)->Start().ok());
  Step(clock, rec, (*gen)->base(), t0, 0, 100);
  (*gen)->Wait();
  EXPECT_THAT(ends, ElementsAre(0)) << "the run's end, once, nothing skipped";
  ASSERT_EQ(rec.edges.size(), 100u);
  for (int k = 0; k < 100; ++k) {
    EXPECT_EQ(rec.edges[k].slot, k);
    EXPECT_EQ(rec.edges[k].scheduled_ns, t0 + (*gen)->base().SlotStartNs(k));
    EXPECT_EQ(rec.edges[k].actual_ns, rec.edges[k].scheduled_ns);
  }
  EXPECT_EQ(rec.edges[1].scheduled_ns - t0, 1'096'491);
  EXPECT_EQ(rec.edges[3].scheduled_ns - t0, 3'289'474);
  EXPECT_EQ((*gen)->stats().edges, 100u);
  EXPECT_EQ((*gen)->stats().missed, 0u);
}

TEST(SlotClockTest, NoDriftAfterTwentyFourHours) {
  const int64_t day = 912LL * 86400;
  SimClock clock(0);
  auto gen = SlotClock::Create({.slot_rate_hz = 912, .t0_ns = 0, .first_slot = day - 2, .slot_count = 5}, &clock);
  ASSERT_TRUE(gen.ok());
  Recorder rec;
  (*gen)->AddListener([&](const SlotEdge& e) { rec(e); });
  ASSERT_TRUE((*gen)->Start().ok());
  Step(clock, rec, (*gen)->base(), 0, day - 2, 5);
  (*gen)->Wait();
  ASSERT_EQ(rec.edges.size(), 5u);
  // Slot 912 * 86400 is exactly 24 h after slot 0.
  EXPECT_EQ(rec.edges[2].slot, day);
  EXPECT_EQ(rec.edges[2].scheduled_ns, 86'400'000'000'000);
  // Its neighbours are a slot away, to the rounding of each edge on its own.
  EXPECT_EQ(rec.edges[2].scheduled_ns - rec.edges[1].scheduled_ns, 1'096'491);
  EXPECT_EQ(rec.edges[3].scheduled_ns - rec.edges[2].scheduled_ns, 1'096'491);
}

TEST(SlotClockTest, LockstepDeliversEveryEdgeEvenWhenTimeJumps) {
  SimClock clock(0);
  auto gen = SlotClock::Create({.slot_rate_hz = 1000, .slot_count = 10}, &clock);
  ASSERT_TRUE(gen.ok());
  Recorder rec;
  (*gen)->AddListener([&](const SlotEdge& e) { rec(e); });
  ASSERT_TRUE((*gen)->Start().ok());
  clock.AdvanceTo(20'000'000);  // 20 slots at once
  (*gen)->Wait();
  ASSERT_EQ(rec.edges.size(), 10u);
  for (int k = 0; k < 10; ++k) EXPECT_EQ(rec.edges[k].slot, k);
  EXPECT_EQ((*gen)->stats().missed, 0u);
}

TEST(SlotClockTest, RealTimeEdgesAreNeverEarly) {
  const int64_t t0 = HostClockNs(false) + 5'000'000;
  auto gen = SlotClock::Create({.slot_rate_hz = 912, .t0_ns = t0, .slot_count = 60});
  ASSERT_TRUE(gen.ok());
  Recorder rec;
  (*gen)->AddListener([&](const SlotEdge& e) { rec(e); });
  ASSERT_TRUE((*gen)->Start().ok());
  (*gen)->Wait();
  const SlotClockStats stats = (*gen)->stats();
  EXPECT_EQ(stats.edges + stats.missed, 60u);
  EXPECT_EQ(rec.edges.size(), stats.edges);
  for (const SlotEdge& e : rec.edges) {
    EXPECT_GE(e.actual_ns, e.scheduled_ns) << "slot " << e.slot;
    EXPECT_EQ(e.scheduled_ns, t0 + (*gen)->base().SlotStartNs(e.slot));
  }
}

TEST(SlotClockTest, RealTimeMissesEdgesItIsASlotLateForAndCountsThem) {
  const int64_t t0 = HostClockNs(false) + 2'000'000;
  auto gen = SlotClock::Create({.slot_rate_hz = 1000, .t0_ns = t0, .slot_count = 30});
  ASSERT_TRUE(gen.ok());
  Recorder rec;
  int64_t stalled_at = -1;
  (*gen)->AddListener([&](const SlotEdge& e) {
    rec(e);
    // A listener that holds the thread for 5.5 slots, once, at the first edge from slot 3 on.
    if (e.slot >= 3 && stalled_at < 0) {
      stalled_at = e.slot;
      std::this_thread::sleep_for(std::chrono::microseconds(5500));
    }
  });
  std::vector<int64_t> ends;
  (*gen)->AddEndListener([&](int64_t missed_at_end) { ends.push_back(missed_at_end); });
  ASSERT_TRUE((*gen)->Start().ok());
  (*gen)->Wait();
  const SlotClockStats stats = (*gen)->stats();
  EXPECT_EQ(stats.edges + stats.missed, 30u);
  int64_t reported_missing = 0;
  for (const SlotEdge& e : rec.edges) {
    // Nothing is delivered a whole slot late.
    EXPECT_LT(e.actual_ns - e.scheduled_ns, 1'000'000) << "slot " << e.slot;
    reported_missing += e.missed_before;
  }
  // Every missed edge is reported by the next delivered one; edges missed after the last delivered one (a loaded
  // machine can stall the thread again near the end) by the run's end, once.
  ASSERT_FALSE(rec.edges.empty());
  ASSERT_EQ(ends.size(), 1u);
  EXPECT_EQ(ends[0], 29 - rec.edges.back().slot);
  EXPECT_EQ(static_cast<uint64_t>(reported_missing + ends[0]), stats.missed);
  ASSERT_GE(stalled_at, 3);
  ASSERT_LT(stalled_at, 25) << "the machine is too loaded to reach slot 3 within 22 slots";
  size_t i = 0;
  while (rec.edges[i].slot != stalled_at) ++i;
  ASSERT_LT(i + 1, rec.edges.size());
  const SlotEdge& after = rec.edges[i + 1];
  // The stall (5.5 slots) covered at least four edges: none of them was delivered late, all of them are counted.
  EXPECT_GE(after.slot, stalled_at + 5);
  EXPECT_EQ(after.missed_before, after.slot - stalled_at - 1);
  EXPECT_GE(stats.missed, 4u);
}

TEST(SlotClockTest, StopEndsAnUnboundedClock) {
  auto gen = SlotClock::Create({.slot_rate_hz = 1, .t0_ns = HostClockNs(false)});
  ASSERT_TRUE(gen.ok());
  bool ended = false;
  (*gen)->AddEndListener([&](int64_t) { ended = true; });
  ASSERT_TRUE((*gen)->Start().ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  (*gen)->Stop();  // the next edge is up to a second away: the sleep is cut short (a hang would time the test out)
  EXPECT_LE((*gen)->stats().edges, 1u);
  EXPECT_FALSE(ended) << "a stopped clock's run did not end";
  SimClock clock(0);
  auto virt = SlotClock::Create({.slot_rate_hz = 912}, &clock);
  ASSERT_TRUE(virt.ok());
  ASSERT_TRUE((*virt)->Start().ok());
  (*virt)->Stop();  // parked in SleepUntilNs: Interrupt() wakes it
}

TEST(SlotClockTest, OptionsAreValidated) {
  EXPECT_THAT(std::string(SlotClockOptions{.slot_rate_hz = 0}.Validate().message()), ::testing::HasSubstr("slot_rate_hz 0"));
  EXPECT_THAT(std::string(SlotClockOptions{.spin_ns = 2'000'000}.Validate().message()), ::testing::HasSubstr("spin_ns"));
  EXPECT_THAT(std::string(SlotClockOptions{.realtime_priority = 120}.Validate().message()),
              ::testing::HasSubstr("realtime_priority 120"));
  EXPECT_FALSE(SlotClock::Create({.first_slot = -1}).ok());
}

}  // namespace
}  // namespace stage::timing
