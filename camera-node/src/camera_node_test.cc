// Camera node: settings from the rig, configuration through the device, frame counting.
#include "camera_node.h"

#include <filesystem>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/clock.h"
#include "stage/common/rig.h"
#include "stage/sim/sim_camera_device.h"
#include "stage/timing/time_base.h"

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

// A take through the node: armed, frames on the take's slots recorded (one in a slot the camera does not fire in is
// not), finished with every expected slot accounted for; a second arm while armed and an unknown take are refused.
TEST(CameraNodeTest, ArmRecordsTheTakesFramesAndFinishAccountsForEverySlot) {
  SimClock clock;
  auto node = CameraNode::Create(TestCamera(), std::make_unique<sim::SimCameraDevice>(&clock, "sn-1"), "abc");
  ASSERT_TRUE(node.ok()) << node.status();
  const std::string dir = ::testing::TempDir() + "/camera-node-take";
  std::filesystem::remove_all(dir);
  v1::ArmCameraRequest arm;
  arm.set_take_id("fastage-20261123-0001");
  arm.set_take_dir(dir);
  arm.set_slot_count(76);
  arm.set_patterns_per_cycle(38);
  arm.set_slot_rate_hz(912);
  arm.set_t0_bus_ns(1'000'000'000);
  arm.set_trigger_delay_ns(15'000);
  arm.mutable_trigger_plan()->set_divider(38);
  arm.mutable_trigger_plan()->set_slot_phase(19);
  v1::SchedulePattern* full = arm.add_patterns();
  full->set_name("full-parallel");
  full->set_polarization(v1::POLARIZATION_PARALLEL);
  // The controller's copy of the settings must be the node's: a different exposure is refused, naming the field.
  *arm.mutable_camera() = TestCamera();
  arm.mutable_camera()->set_exposure_us(TestCamera().exposure_us() + 100);
  auto refused = (*node)->Arm(arm);
  EXPECT_TRUE(absl::IsFailedPrecondition(refused.status()));
  EXPECT_THAT(refused.status().message(), ::testing::HasSubstr("exposure_us"));
  *arm.mutable_camera() = TestCamera();
  auto armed = (*node)->Arm(arm);
  ASSERT_TRUE(armed.ok()) << armed.status();
  EXPECT_EQ(armed->expected_frames(), 2);
  // Asked again for the same take (a controller that did not hear the answer), it answers the same; another take is
  // refused while this one is armed.
  auto again = (*node)->Arm(arm);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->expected_frames(), 2);
  EXPECT_EQ(again->path(), armed->path());
  v1::ArmCameraRequest other = arm;
  other.set_take_id("fastage-20261123-0002");
  EXPECT_TRUE(absl::IsFailedPrecondition((*node)->Arm(other).status()));
  const auto base = timing::TimeBase::Create(912);
  for (int64_t slot : {19, 20, 57}) {
    auto frame = std::make_shared<Frame>();
    frame->frame_id = static_cast<uint64_t>(slot);
    frame->device_timestamp_ns = 1'000'000'000 + base->SlotStartNs(slot) + 15'000;
    frame->width = 8;
    frame->height = 4;
    frame->data.assign(32, static_cast<uint8_t>(slot));
    (*node)->OnFrame(frame);
  }
  EXPECT_EQ((*node)->Stats().take_frames_received(), 2);  // slot 20 is not one it fires in: not the take's
  EXPECT_EQ((*node)->Stats().take_frames_expected(), 2);
  v1::FinishCameraRequest finish;
  finish.set_take_id("other");
  EXPECT_TRUE(absl::IsNotFound((*node)->Finish(finish).status()));
  finish.set_take_id(arm.take_id());
  finish.set_drain_ms(100);
  auto report = (*node)->Finish(finish);
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_EQ(report->frames_written(), 2);
  EXPECT_EQ(report->frames_unmatched(), 1);
  ASSERT_EQ(report->slots_size(), 2);
  EXPECT_EQ(report->slots(1).slot(), 57);
  EXPECT_EQ(report->slots(1).reason(), 0);
  EXPECT_EQ(report->slots(1).pattern(), 19);
  EXPECT_EQ(report->path(), dir + "/cameras/mv-01.h5");
  EXPECT_TRUE(std::filesystem::exists(report->path()));
  // What the pattern indexes mean, and the calibration, are in the file.
  auto file = storage::FrameFileReader::Open(report->path());
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_THAT((*file)->info().patterns_json,
              ::testing::HasSubstr(R"("name":"full-parallel","polarization":"parallel")"));
  EXPECT_THAT((*file)->info().calibration_json, ::testing::HasSubstr("intrinsics"));
  EXPECT_EQ((*node)->Stats().take_id(), "");
}

TEST(CameraNodeTest, InfoAndStats) {
  SimClock clock;
  auto node = CameraNode::Create(TestCamera(), std::make_unique<sim::SimCameraDevice>(&clock, "sn-1"), "abc");
  ASSERT_TRUE(node.ok()) << node.status();
  v1::NodeInfo info = (*node)->Info();
  EXPECT_EQ(info.id(), "mv-01");
  EXPECT_EQ(info.kind(), v1::NODE_KIND_CAMERA);
  EXPECT_EQ(info.camera_role(), v1::CAMERA_ROLE_MACHINE_VISION);
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
