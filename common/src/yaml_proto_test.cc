// The generic YAML -> protobuf conversion, on the node.proto and rig.proto messages.
#include "stage/common/yaml_proto.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/v1/rig.pb.h"

namespace stage {
namespace {

using ::testing::HasSubstr;
using ::testing::StartsWith;

TEST(YamlProtoTest, FillsNestedMessagesListsMapsAndEnums) {
  v1::CameraConfig camera;
  SourceMap map;
  ASSERT_TRUE(ParseYamlToProto(R"(
id: c1
role: HIGH_SPEED
pixel_format: Bayer-RG8
width: 16
features: {Gamma: "1.0", BlackLevel: "4"}
pose: {position_mm: [1, 2.5, -3]}
)",
                               "c.yaml", &camera, &map)
                  .ok());
  EXPECT_EQ(camera.id(), "c1");
  EXPECT_EQ(camera.role(), v1::CAMERA_ROLE_HIGH_SPEED);
  EXPECT_EQ(camera.pixel_format(), v1::PIXEL_FORMAT_BAYER_RG8);
  EXPECT_TRUE(camera.has_width());
  EXPECT_FALSE(camera.has_height());
  EXPECT_EQ(camera.features().at("Gamma"), "1.0");
  EXPECT_EQ(camera.pose().position_mm().y(), 2.5);
  EXPECT_EQ(camera.pose().position_mm().z(), -3);
  EXPECT_EQ(map.Find("width").line, 5);
  EXPECT_EQ(map.Find("pose.position_mm.y").line, 7);
  // A path never written resolves to its nearest written ancestor.
  EXPECT_EQ(map.Find("pose.look_at_mm.x").line, 7);
  EXPECT_EQ(map.Find("trigger.divider").line, 0);
}

TEST(YamlProtoTest, NullLeavesFieldUnset) {
  v1::CameraConfig camera;
  ASSERT_TRUE(ParseYamlToProto("id: c1\nwidth: ~\npose:\n", "c.yaml", &camera, nullptr).ok());
  EXPECT_FALSE(camera.has_width());
  EXPECT_FALSE(camera.has_pose());
}

TEST(YamlProtoTest, BooleansAreStrict) {
  v1::GpiodLightSettings s;
  ASSERT_TRUE(ParseYamlToProto("drives_slot_clock: yes", "g.yaml", &s, nullptr).ok());
  EXPECT_TRUE(s.drives_slot_clock());
  absl::Status bad = ParseYamlToProto("drives_slot_clock: maybe", "g.yaml", &s, nullptr);
  EXPECT_THAT(std::string(bad.message()),
              StartsWith("g.yaml:1:20: drives_slot_clock: \"maybe\" is not a boolean (true or false)"));
}

TEST(YamlProtoTest, IntegerOverflowIsAnError) {
  v1::CameraConfig camera;
  absl::Status s = ParseYamlToProto("width: 5000000000", "c.yaml", &camera, nullptr);
  EXPECT_THAT(std::string(s.message()), HasSubstr("width: \"5000000000\" is not an integer >= 0 (out of range"));
}

TEST(YamlProtoTest, NonFiniteNumbersAreRejected) {
  v1::CameraConfig camera;
  absl::Status s = ParseYamlToProto("exposure_us: .nan", "c.yaml", &camera, nullptr);
  EXPECT_THAT(std::string(s.message()), HasSubstr("exposure_us: \".nan\" is not a number"));
}

TEST(YamlProtoTest, TopLevelMustBeAMap) {
  v1::CameraConfig camera;
  absl::Status s = ParseYamlToProto("- a\n- b\n", "c.yaml", &camera, nullptr);
  EXPECT_THAT(std::string(s.message()), StartsWith("c.yaml:1:1: expected a map of CameraConfig fields, got a list"));
}

TEST(YamlProtoTest, ScalarWhereMessageExpected) {
  v1::CameraConfig camera;
  absl::Status s = ParseYamlToProto("trigger: fast", "c.yaml", &camera, nullptr);
  EXPECT_THAT(std::string(s.message()),
              StartsWith("c.yaml:1:10: trigger: expected a map of TriggerConfig fields, got a scalar"));
}

TEST(YamlProtoTest, FormatConfigErrorLeavesOutUnknownParts) {
  EXPECT_EQ(FormatConfigError("f.yaml", {}, "", "bad"), "f.yaml: bad");
  EXPECT_EQ(FormatConfigError("f.yaml", {3, 0}, "a.b", "bad"), "f.yaml:3: a.b: bad");
  EXPECT_EQ(FormatConfigError("f.yaml", {3, 7}, "a.b", "bad"), "f.yaml:3:7: a.b: bad");
}

}  // namespace
}  // namespace stage
