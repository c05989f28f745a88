// Light node: info, stats from the driver, and dark on destruction.
#include "light_node.h"

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
