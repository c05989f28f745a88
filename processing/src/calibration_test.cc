// ResolveCamera: the recorded frames' size is checked against what the take recorded (its render scale), in both axes.
#include "stage/processing/calibration.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

// The shipped rig with hs-2 as a 1920 x 1080 camera, recorded at `render_scale`.
LoadedRig SmallSensorRig(double render_scale) {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok()) << rig.status();
  auto set = ApplyRigOverrides(*rig, {"cameras[hs-2].width=1920", "cameras[hs-2].height=1080",
                                      "sim.render_scale=" + std::to_string(render_scale)});
  EXPECT_TRUE(set.ok()) << set.status();
  return *set;
}

TEST(ResolveCameraTest, FramesWhoseSizeRoundsUnevenlyAreTheTakesRenderScale) {
  // 1920 x 1080 at 0.02 renders 38.4 x 21.6: 38 x 22. Its width alone says 0.0198, whose height would be 21.
  const LoadedRig rig = SmallSensorRig(0.02);
  auto light = LightModel::FromRig(rig);
  ASSERT_TRUE(light.ok()) << light.status();
  auto setup = ResolveCamera(rig, *light, "hs-2", 38, 22, 8);
  ASSERT_TRUE(setup.ok()) << setup.status();
  EXPECT_EQ(setup->model.width(), 38);
  EXPECT_EQ(setup->model.height(), 22);
  EXPECT_EQ(setup->camera.rays.size(), 38u * 22u);
}

TEST(ResolveCameraTest, TheWholeSensorIsAcceptedAndAnyOtherSizeRefusedNamingBoth) {
  const LoadedRig rig = SmallSensorRig(0.02);
  auto light = LightModel::FromRig(rig);
  ASSERT_TRUE(light.ok()) << light.status();
  EXPECT_TRUE(ResolveCamera(rig, *light, "hs-2", 1920, 1080, 8).ok());
  auto bad = ResolveCamera(rig, *light, "hs-2", 38, 21, 8);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(bad.status().message()),
              HasSubstr("camera \"hs-2\": its frames are 38x21, but its sensor of 1920x1080 gives 38x22 at the take's "
                        "render scale 0.02 or 1920x1080 (the whole sensor)"));
}

}  // namespace
}  // namespace stage::processing
