// What-if overrides: paths, selectors, values by the rig file's rules, and errors that name what is wrong.
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"

namespace stage {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

LoadedRig Shipped() {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok()) << rig.status();
  return *rig;
}

TEST(RigOverrideTest, ScalarsEnumsAndSelectors) {
  auto rig = ApplyRigOverrides(
      Shipped(), {"timing.led_switch_delay_us=60", "cameras[hs-2].exposure_us = 850", "cameras[*].link=gige-1",
                  "cameras[0].trigger.delay_us=70", "light_nodes[lights-gpio-2].unit_limits.max_duty_cycle=0.4"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  const v1::RigConfig& r = rig->rig;
  EXPECT_EQ(r.timing().led_switch_delay_us(), 60);
  EXPECT_EQ(r.cameras(25).id(), "hs-2");
  EXPECT_EQ(r.cameras(25).exposure_us(), 850);
  EXPECT_EQ(r.cameras(24).exposure_us(), 900);
  for (const auto& c : r.cameras()) EXPECT_EQ(c.link(), v1::LINK_KIND_GIGE_1) << c.id();
  EXPECT_TRUE(r.cameras(0).trigger().has_delay_us());
  EXPECT_EQ(r.cameras(0).trigger().delay_us(), 70);
  // Setting one field of a message keeps its siblings.
  EXPECT_EQ(r.cameras(0).trigger().divider(), 38u);
  EXPECT_EQ(r.light_nodes(5).unit_limits().max_duty_cycle(), 0.4);
  EXPECT_EQ(r.light_nodes(5).unit_limits().max_current_ma(), 700);
  EXPECT_THAT(rig->source_name, HasSubstr("with timing.led_switch_delay_us=60"));
}

// An index one past the end adds an entry (a fault on a rig without faults); the fields of a fake GigE Vision camera
// are checked against the rig's cameras.
TEST(RigOverrideTest, AnIndexPastTheEndAddsAnEntry) {
  auto rig = ApplyRigOverrides(
      Shipped(), {"sim.gige_fakes=true", "cameras[mv-*].backend=sim", "cameras[mv-02].backend=aravis", "cameras[mv-02].device=127.0.0.12",
                  "sim.faults[0].target=mv-02", "sim.faults[0].packet_loss=0.001", "sim.faults[1].target=hs-1",
                  "sim.faults[1].miss_triggers=0.5"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  ASSERT_EQ(rig->rig.sim().faults_size(), 2);
  EXPECT_EQ(rig->rig.sim().faults(0).packet_loss(), 0.001);
  EXPECT_EQ(rig->rig.sim().faults(1).target(), "hs-1");
  auto bad = ApplyRigOverrides(Shipped(), {"sim.faults[0].target=mv-02", "sim.faults[0].packet_loss=0.001"});
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("apply to a fake GigE Vision camera"));
  auto shared = ApplyRigOverrides(
      Shipped(), {"sim.gige_fakes=true", "cameras[mv-*].backend=sim", "cameras[mv-01].backend=aravis",
                  "cameras[mv-02].backend=aravis", "cameras[mv-01].device=127.0.0.12", "cameras[mv-02].device=127.0.0.12"});
  ASSERT_FALSE(shared.ok());
  EXPECT_THAT(shared.status().message(), HasSubstr("one fake camera per address"));
}

TEST(RigOverrideTest, GlobsSelectByIdPattern) {
  auto rig = ApplyRigOverrides(Shipped(), {"cameras[mv-*].link=gige-2-5"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  for (const auto& c : rig->rig.cameras()) {
    EXPECT_EQ(c.link(), c.role() == v1::CAMERA_ROLE_HIGH_SPEED ? v1::LINK_KIND_ON_CAMERA_RAM : v1::LINK_KIND_GIGE_2_5)
        << c.id();
  }
  v1::RigConfig r = Shipped().rig;
  EXPECT_THAT(std::string(ApplyRigOverride(&r, "cameras[xx-*].gain_db=1").message()),
              HasSubstr("no cameras entry with id \"xx-*\""));
}

TEST(RigOverrideTest, ListsAreReplacedWhole) {
  v1::RigConfig rig = Shipped().rig;
  ASSERT_TRUE(ApplyRigOverride(&rig, "light_nodes[lights-gpio-1].units[0].direction=[0, 0, 1]").ok());
  EXPECT_EQ(rig.light_nodes(4).units(0).direction().z(), 1);
  EXPECT_EQ(rig.light_nodes(4).units(0).direction().x(), 0);
}

TEST(RigOverrideTest, ErrorsNameTheProblem) {
  v1::RigConfig rig = Shipped().rig;
  auto message = [&](const char* a) { return std::string(ApplyRigOverride(&rig, a).message()); };
  EXPECT_THAT(message("timing.led_delay_us=3"),
              AllOf(HasSubstr("--set timing.led_delay_us=3: TimingConfig has no field \"led_delay_us\""),
                    HasSubstr("led_switch_delay_us")));
  EXPECT_THAT(message("cameras[hs-9].exposure_us=1"),
              AllOf(HasSubstr("no cameras entry with id \"hs-9\""), HasSubstr("hs-1")));
  EXPECT_THAT(message("cameras[99].exposure_us=1"), HasSubstr("index out of range (27 entries)"));
  EXPECT_THAT(message("cameras.exposure_us=1"), HasSubstr("cameras is a list: select entries"));
  EXPECT_THAT(message("cameras[hs-1].exposure_us=fast"), AllOf(HasSubstr("exposure_us"), HasSubstr("fast")));
  EXPECT_THAT(message("cameras[hs-1].link=gige-7"), HasSubstr("gige-7"));
  EXPECT_THAT(message("cameras[hs-1].width=-5"), HasSubstr("width"));
  EXPECT_THAT(message("timing"), HasSubstr("expected path=value"));
  EXPECT_THAT(message("timing.slot_rate_hz.x=1"), HasSubstr("slot_rate_hz is not a message"));
}

TEST(RigOverrideTest, AnEmptyListSelectsNothingAndSaysSo) {
  v1::RigConfig rig = Shipped().rig;
  rig.clear_processing_workers();
  EXPECT_THAT(std::string(ApplyRigOverride(&rig, "processing_workers[*].threads=2").message()),
              HasSubstr("processing_workers[*] selects no entries"));
  rig.mutable_light_nodes(0)->clear_units();
  EXPECT_THAT(std::string(ApplyRigOverride(&rig, "light_nodes[0].units[*].intensity_scale=2").message()),
              HasSubstr("units[*] selects no entries"));
}

TEST(RigOverrideTest, ATakeTooLongForTheExactTimeBaseIsRefused) {
  // 99991 slots/s (a prime) makes ticks of 1/(99991 * 10^9) s: 64 bits hold about 11 hours of them.
  auto rig = ApplyRigOverrides(
      Shipped(), {"timing.slot_rate_hz=99991", "timing.take_length_s=86400", "cameras[*].exposure_us=5",
                  "cameras[*].frame_rate_hz=99991", "timing.led_switch_delay_us=0", "timing.led_settle_us=0"});
  ASSERT_FALSE(rig.ok());
  EXPECT_THAT(rig.status().message(), AllOf(HasSubstr("timing.take_length_s: 86400 s does not fit the exact time base"),
                                            HasSubstr("at most 40004 s")));
}

TEST(RigOverrideTest, TheResultIsValidated) {
  auto rig = ApplyRigOverrides(Shipped(), {"cameras[hs-1].exposure_us=0"});
  ASSERT_FALSE(rig.ok());
  EXPECT_THAT(rig.status().message(), AllOf(HasSubstr("with cameras[hs-1].exposure_us=0 is not valid"),
                                            HasSubstr("cameras[24].exposure_us: 0 is not > 0")));
}

}  // namespace
}  // namespace stage
