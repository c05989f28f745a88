// Light node: info, stats from the driver, and dark on destruction.
#include "light_node.h"

#include "absl/strings/str_cat.h"
#include "backends.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/sim/sim_light_driver.h"

namespace stage::light {
namespace {

v1::LightNodeConfig TestNode() {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok());
  return rig->rig.light_nodes(0);
}

TEST(LightNodeTest, InfoAndStats) {
  v1::LightNodeConfig config = TestNode();
  auto node =
      LightNode::Create(config, std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count()), "h");
  ASSERT_TRUE(node.ok()) << node.status();
  EXPECT_EQ((*node)->Info().id(), config.id());
  EXPECT_EQ((*node)->Info().kind(), v1::NODE_KIND_LIGHT);
  EXPECT_EQ((*node)->Info().backend(), "sim");
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_IDLE);
}

TEST(LightNodeTest, ArmLoadsTheTableStepsFromItsFirstRowAndDisarmGoesDark) {
  v1::LightNodeConfig config = TestNode();
  auto driver = std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count());
  sim::SimLightDriver* sim = driver.get();
  auto node = LightNode::Create(config, std::move(driver), "h");
  ASSERT_TRUE(node.ok());
  v1::PatternTable table;
  for (int r = 0; r < 3; ++r) {
    v1::PatternRow* row = table.add_rows();
    row->set_name(absl::StrCat("p", r));
    for (uint32_t c = 0; c < config.channel_count(); ++c) row->add_levels(static_cast<uint32_t>(1000 * r + c));
  }
  ASSERT_TRUE((*node)->Arm("t1", table).ok());
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_ARMED);
  sim->Step();
  sim->Step();
  EXPECT_EQ(sim->Outputs()[2], 1002);  // row 1 on the second edge
  // Armed again for the next take: back to the first row, whatever it was on.
  ASSERT_TRUE((*node)->Arm("t2", table).ok());
  sim->Step();
  EXPECT_EQ(sim->Outputs()[2], 2);
  ASSERT_TRUE((*node)->Disarm("t2").ok());
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_IDLE);
  EXPECT_EQ(sim->Outputs()[2], 0);
  table.mutable_rows(1)->set_levels(5, 70000);
  const absl::Status bad = (*node)->Arm("t3", table);
  EXPECT_TRUE(absl::IsInvalidArgument(bad));
  EXPECT_NE(bad.message().find("row 1 (p1) channel 5: level 70000 is above 65535"), std::string::npos) << bad;
}

TEST(LightNodeTest, ChannelCountMismatchIsRefused) {
  v1::LightNodeConfig config = TestNode();
  auto node = LightNode::Create(config, std::make_unique<sim::SimLightDriver>(config.id(), 3), "h");
  EXPECT_FALSE(node.ok());
}

TEST(LightNodeTest, BackendsByName) {
  EXPECT_EQ(*ParseLightBackend("modbus"), v1::LIGHT_BACKEND_MODBUS);
  EXPECT_FALSE(ParseLightBackend("dmx").ok());
  v1::LightNodeConfig config = TestNode();
  EXPECT_TRUE(CreateLightDriver(v1::LIGHT_BACKEND_SIM, config).ok());
  // Hardware drivers are not written yet: asking for one must fail loudly, not fall back to the sim.
  auto modbus = CreateLightDriver(v1::LIGHT_BACKEND_MODBUS, config);
  ASSERT_FALSE(modbus.ok());
  EXPECT_EQ(modbus.status().code(), absl::StatusCode::kUnimplemented);
}

}  // namespace
}  // namespace stage::light
