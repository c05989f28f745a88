// SimLightDriver: table checks, stepping through rows on slot edges, blackout latch.
#include "stage/sim/sim_light_driver.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::sim {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

light::PatternTable Table() { return {"test", {"a", "b", "c"}, {{1, 2}, {3, 4}, {5, 6}}}; }

TEST(SimLightDriverTest, StepsThroughRowsWhenArmed) {
  SimLightDriver d("n", 2);
  EXPECT_FALSE(d.Arm().ok());  // no table yet
  ASSERT_TRUE(d.LoadPatternTable(Table()).ok());
  d.Step();  // not armed: nothing happens
  EXPECT_THAT(d.Outputs(), ElementsAre(0, 0));
  ASSERT_TRUE(d.Arm().ok());
  d.Step();
  EXPECT_THAT(d.Outputs(), ElementsAre(1, 2));
  d.Step();
  d.Step();
  EXPECT_THAT(d.Outputs(), ElementsAre(5, 6));
  d.Step();  // wraps around
  EXPECT_THAT(d.Outputs(), ElementsAre(1, 2));
  EXPECT_EQ(d.State().steps, 4u);
}

TEST(SimLightDriverTest, RejectsRowsOfTheWrongWidth) {
  SimLightDriver d("lights-a", 3);
  absl::Status s = d.LoadPatternTable(Table());
  EXPECT_THAT(std::string(s.message()), HasSubstr("light node \"lights-a\": pattern table row 0 has 2 levels"));
}

TEST(SimLightDriverTest, BlackoutLatchesUntilReset) {
  SimLightDriver d("n", 2);
  ASSERT_TRUE(d.LoadPatternTable(Table()).ok());
  ASSERT_TRUE(d.Arm().ok());
  d.Step();
  ASSERT_TRUE(d.Blackout().ok());
  EXPECT_THAT(d.Outputs(), ElementsAre(0, 0));
  d.Step();
  EXPECT_THAT(d.Outputs(), ElementsAre(0, 0));
  EXPECT_FALSE(d.Arm().ok());  // latched
  ASSERT_TRUE(d.ResetBlackout().ok());
  EXPECT_TRUE(d.Arm().ok());
}

TEST(SimLightDriverTest, StartsAtAPlannedEdgeOnlyWhenArmedAndSeesNoClockOutsideAWorld) {
  SimLightDriver d("lights-a", 2);
  ASSERT_TRUE(d.LoadPatternTable(Table()).ok());
  EXPECT_THAT(std::string(d.StartAt(0).message()), HasSubstr("start a table only when armed"));
  ASSERT_TRUE(d.Arm().ok());
  EXPECT_TRUE(d.StartAt(light::kStartNotYet).ok());
  EXPECT_THAT(std::string(d.SlotClockInput().status().message()), HasSubstr("not in a world"));
}

}  // namespace
}  // namespace stage::sim
