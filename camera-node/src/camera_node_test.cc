// Camera node: settings from the rig, configuration through the device, frame counting.
#include "camera_node.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/clock.h"
#include "stage/common/rig.h"
#include "stage/sim/sim_camera_device.h"

namespace stage::camera {
namespace {

using ::testing::HasSubstr;

v1::CameraConfig TestCamera() {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok());
  return rig->rig.cameras(0);
}

TEST(CameraNodeTest, SettingsFollowTheRig) {
  auto s = SettingsFromConfig(TestCamera());
  ASSERT_TRUE(s.ok());
  EXPECT_EQ(s->width, 2592u);
  EXPECT_EQ(s->pixel_format, "BayerRG8");
  EXPECT_EQ(s->trigger, TriggerMode::kHardware);
  EXPECT_EQ(s->exposure_us, 900);
}

TEST(CameraNodeTest, InfoAndStats) {
  SimClock clock;
  auto node = CameraNode::Create(TestCamera(), std::make_unique<sim::SimCameraDevice>(&clock, "sn-1"), "abc");
  ASSERT_TRUE(node.ok()) << node.status();
  v1::NodeInfo info = (*node)->Info();
  EXPECT_EQ(info.id(), "mv-01");
  EXPECT_EQ(info.kind(), v1::NODE_KIND_CAMERA);
  EXPECT_EQ(info.role(), "machine-vision");
  EXPECT_EQ(info.backend(), "sim");
  EXPECT_EQ(info.rig_hash(), "abc");
  EXPECT_GT(info.pid(), 0);
  auto frame = std::make_shared<Frame>();
  frame->data.resize(10);
  (*node)->OnFrame(frame);
  (*node)->OnFrame(frame);
  EXPECT_EQ((*node)->Stats().frames_completed(), 2u);
}

TEST(CameraNodeTest, DeviceRejectionNamesTheCamera) {
  v1::CameraConfig config = TestCamera();
  config.set_exposure_us(50000);  // longer than the 24 fps frame period
  SimClock clock;
  auto node = CameraNode::Create(config, std::make_unique<sim::SimCameraDevice>(&clock, "sn-1"), "");
  ASSERT_FALSE(node.ok());
  EXPECT_THAT(std::string(node.status().message()), HasSubstr("camera \"mv-01\": sim camera sn-1: exposure 50000 us"));
}

}  // namespace
}  // namespace stage::camera
