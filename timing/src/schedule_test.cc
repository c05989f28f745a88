// The schedule compiler on the shipped rig: offsets, multi-rate cameras, pattern tables, the stable hash.
#include "stage/timing/schedule.h"

#include <cmath>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"

namespace stage::timing {
namespace {

struct Compiled {
  LoadedRig rig;
  PatternSet patterns;
  v1::Schedule schedule;
};

Compiled CompileShipped(void (*edit)(v1::RigConfig*) = nullptr) {
  Compiled c;
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok()) << rig.status();
  c.rig = *rig;
  if (edit != nullptr) edit(&c.rig.rig);
  auto set = LoadRigPatternSet(c.rig.rig, c.rig.base_dir);
  EXPECT_TRUE(set.ok()) << set.status();
  c.patterns = *set;
  auto schedule = CompileSchedule(c.rig.rig, c.patterns);
  EXPECT_TRUE(schedule.ok()) << schedule.status();
  c.schedule = *schedule;
  return c;
}

TEST(ScheduleTest, ShippedRigOffsets) {
  Compiled c = CompileShipped();
  const v1::Schedule& s = c.schedule;
  const TimeBase base = TimeBase::FromProto(s.time_base());
  EXPECT_EQ(s.pattern_set(), "fastage-38");
  EXPECT_EQ(s.patterns_size(), 38);
  EXPECT_EQ(s.light_nodes_size(), 6);
  EXPECT_EQ(s.cameras_size(), 27);
  EXPECT_EQ(s.take_slots(), 9120);  // 10 s at 912 Hz
  // switch 20 + max(rise 5, fall 5) + settle 30 = 55 us after the slot edge.
  for (const auto& n : s.light_nodes()) {
    EXPECT_EQ(n.switch_ticks(), base.UsToTicks(20)) << n.id();
    EXPECT_EQ(n.steady_start_ticks(), base.UsToTicks(55)) << n.id();
  }
  EXPECT_EQ(s.steady_start_ticks(), base.UsToTicks(55));
  EXPECT_EQ(s.steady_end_ticks(), base.ticks_per_slot() + base.UsToTicks(20));
  EXPECT_EQ(s.guard_ticks(), base.UsToTicks(20));

  const v1::CameraTiming* mv = FindCameraTiming(s, "mv-01");
  ASSERT_NE(mv, nullptr);
  EXPECT_EQ(mv->divider(), 38u);
  EXPECT_EQ(mv->slot_phase(), 19u);
  EXPECT_TRUE(mv->trigger_auto());
  EXPECT_EQ(mv->trigger_ticks(), base.UsToTicks(55));
  EXPECT_EQ(mv->exposure_ticks(), base.UsToTicks(900));
  EXPECT_EQ(mv->period_ticks(), 38 * base.ticks_per_slot());
  EXPECT_EQ(mv->frame_bytes(), 2592 * 2048);
  // Slack: the exposure ends at 955 us; the light changes at 1096.491 + 20 us, less the 20 us guard.
  EXPECT_EQ(mv->late_slack_ticks(), base.ticks_per_slot() - base.UsToTicks(955));
  EXPECT_EQ(mv->early_slack_ticks(), 0);

  const v1::CameraTiming* hs = FindCameraTiming(s, "hs-2");
  ASSERT_NE(hs, nullptr);
  EXPECT_EQ(hs->divider(), 1u);
  EXPECT_EQ(hs->period_ticks(), base.ticks_per_slot());
  EXPECT_TRUE(hs->readout_declared());
  EXPECT_EQ(hs->readout_ticks(), base.UsToTicks(1000));
  EXPECT_TRUE(hs->overlap_exposure_readout());
  EXPECT_EQ(hs->frame_bytes(), 4096 * 2304);
}

TEST(ScheduleTest, MultiRateCamerasInDescribedSlots) {
  Compiled c = CompileShipped();
  v1::SlotEntry s19 = DescribeSlot(c.schedule, 19);
  EXPECT_EQ(s19.pattern_name(), "parallel-full");
  EXPECT_EQ(s19.polarization(), v1::POLARIZATION_PARALLEL);
  EXPECT_EQ(s19.frame(), 0);
  EXPECT_EQ(s19.cameras_size(), 27);  // every camera exposes the full-lit slot
  v1::SlotEntry s20 = DescribeSlot(c.schedule, 20);
  EXPECT_THAT(s20.cameras(), ::testing::ElementsAre("hs-1", "hs-2", "hs-3"));
  v1::SlotEntry s57 = DescribeSlot(c.schedule, 38 * 1000 + 19);
  EXPECT_EQ(s57.frame(), 1000);
  EXPECT_EQ(s57.pattern(), 19u);
  EXPECT_EQ(s57.cameras_size(), 27);
  EXPECT_EQ(s57.start_ns(), TimeBase::FromProto(c.schedule.time_base()).SlotStartNs(38 * 1000 + 19));
  const v1::CameraTiming* mv = FindCameraTiming(c.schedule, "mv-05");
  EXPECT_EQ(NextFiringSlot(*mv, 0), 19);
  EXPECT_EQ(NextFiringSlot(*mv, 19), 19);
  EXPECT_EQ(NextFiringSlot(*mv, 20), 57);
  // A take of N slots expects of it the slots 19, 57, ... below N.
  EXPECT_EQ(FiringsInTake(*mv, 19), 0);
  EXPECT_EQ(FiringsInTake(*mv, 20), 1);
  EXPECT_EQ(FiringsInTake(*mv, 912), 24);
  EXPECT_EQ(FiringsInTake(*FindCameraTiming(c.schedule, "hs-1"), 76), 76);
}

TEST(ScheduleTest, UndeclaredReadoutIsTheRestOfThePeriod) {
  Compiled c = CompileShipped([](v1::RigConfig* rig) { rig->mutable_cameras(26)->set_readout_us(0); });
  const TimeBase base = TimeBase::FromProto(c.schedule.time_base());
  const v1::CameraTiming* hs = FindCameraTiming(c.schedule, "hs-3");
  EXPECT_FALSE(hs->readout_declared());
  EXPECT_EQ(hs->readout_ticks(), base.ticks_per_slot() - base.UsToTicks(900));
}

TEST(ScheduleTest, PatternTablesDriveTheEmitterOfThePatternsPolarization) {
  Compiled c = CompileShipped();
  const v1::LightNodeTiming* node = FindLightTiming(c.schedule, "lights-modbus-1");
  ASSERT_NE(node, nullptr);
  ASSERT_EQ(node->table().rows_size(), 38);
  const v1::PatternRow& cross_full = node->table().rows(0);
  const v1::PatternRow& parallel_full = node->table().rows(19);
  EXPECT_EQ(cross_full.name(), "cross-full");
  ASSERT_EQ(cross_full.levels_size(), 64);
  // led-001: parallel channel 0, cross channel 1.
  EXPECT_EQ(cross_full.levels(0), 0u);
  EXPECT_EQ(cross_full.levels(1), 65535u);
  EXPECT_EQ(parallel_full.levels(0), 65535u);
  EXPECT_EQ(parallel_full.levels(1), 0u);
  // led-001 points at (0.080517, 0.996753, 0): x+ is (1 + 0.080517) / 2 of full drive.
  const int xp = c.patterns.Find("cross-x+");
  ASSERT_GE(xp, 0);
  const double x = 0.080517 / std::sqrt(0.080517 * 0.080517 + 0.996753 * 0.996753);
  EXPECT_EQ(node->table().rows(xp).levels(1), static_cast<uint32_t>(std::lround((1 + x) / 2 * 65535)));
  EXPECT_EQ(node->table().rows(xp).levels(0), 0u);
}

TEST(ScheduleTest, HashIsStableAndFollowsTiming) {
  Compiled a = CompileShipped();
  Compiled b = CompileShipped();
  EXPECT_EQ(a.schedule.hash().size(), 16u);
  EXPECT_EQ(a.schedule.hash(), b.schedule.hash());
  EXPECT_EQ(a.schedule.hash(), ScheduleHash(a.schedule));
  // Addresses are deployment detail: the same schedule.
  Compiled addressed =
      CompileShipped([](v1::RigConfig* rig) { rig->mutable_cameras(0)->set_address("10.0.0.5:7000"); });
  EXPECT_EQ(addressed.schedule.hash(), a.schedule.hash());
  // Any timing change is another schedule.
  Compiled longer = CompileShipped([](v1::RigConfig* rig) { rig->mutable_cameras(3)->set_exposure_us(901); });
  EXPECT_NE(longer.schedule.hash(), a.schedule.hash());
  Compiled later = CompileShipped([](v1::RigConfig* rig) { rig->mutable_timing()->set_led_switch_delay_us(21); });
  EXPECT_NE(later.schedule.hash(), a.schedule.hash());
}

TEST(ScheduleTest, PerNodeSwitchDelayAndExplicitTriggerDelay) {
  Compiled c = CompileShipped([](v1::RigConfig* rig) {
    rig->mutable_light_nodes(2)->set_switch_delay_us(60);
    rig->mutable_cameras(0)->mutable_trigger()->set_delay_us(200);
  });
  const TimeBase base = TimeBase::FromProto(c.schedule.time_base());
  EXPECT_EQ(c.schedule.steady_start_node(), c.rig.rig.light_nodes(2).id());
  EXPECT_EQ(c.schedule.steady_start_ticks(), base.UsToTicks(95));
  // The other nodes switch earlier: the light starts changing 20 us after the next edge.
  EXPECT_EQ(c.schedule.steady_end_ticks(), base.ticks_per_slot() + base.UsToTicks(20));
  // Automatic triggers follow the latest node; an explicit delay stays.
  EXPECT_EQ(FindCameraTiming(c.schedule, "mv-02")->trigger_ticks(), base.UsToTicks(95));
  EXPECT_EQ(FindCameraTiming(c.schedule, "mv-01")->trigger_ticks(), base.UsToTicks(200));
  EXPECT_FALSE(FindCameraTiming(c.schedule, "mv-01")->trigger_auto());
}

}  // namespace
}  // namespace stage::timing
