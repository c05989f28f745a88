// Reading a cycle from a frame file: the frames of the asked virtual frame, matched to the patterns by name,
// demosaiced (GenICam BayerRG: R at the first pixel) into RGB; a lost frame or a foreign pattern list is named.
#include "stage/processing/take_frames.h"

#include <filesystem>
#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "shipped_light.h"
#include "stage/common/rig.h"
#include "stage/storage/frame_file.h"

namespace stage::processing {
namespace {

// Two cycles of BayerRG8 frames, 8x6; in slot k every red site reads 10 + k % 38, green 100 + k % 38, blue
// 200 - k % 38. `skip`: a slot left out.
std::string WriteTake(const LightModel& light, const std::string& name, int64_t skip = -1,
                      const std::string& renamed = "") {
  const std::string path = ::testing::TempDir() + "/take-frames-" + name + ".h5";
  std::filesystem::remove(path);
  storage::FrameFileInfo info;
  info.camera_id = "hs-2";
  info.take_id = "t";
  info.width = 8;
  info.height = 6;
  info.bytes_per_pixel = 1;
  info.pixel_format = "BayerRG8";
  nlohmann::json patterns = nlohmann::json::array();
  for (size_t i = 0; i < light.patterns.size(); ++i) {
    patterns.push_back({{"index", i}, {"name", i == 3 && !renamed.empty() ? renamed : light.patterns[i].name}});
  }
  info.patterns_json = patterns.dump();
  auto writer = storage::FrameFileWriter::Create(path, info);
  EXPECT_TRUE(writer.ok()) << writer.status();
  for (int64_t k = 0; k < 76; ++k) {
    if (k == skip) continue;
    std::vector<uint8_t> px(48);
    const int p = static_cast<int>(k % 38);
    for (int y = 0; y < 6; ++y) {
      for (int x = 0; x < 8; ++x) {
        const bool red = y % 2 == 0 && x % 2 == 0, blue = y % 2 == 1 && x % 2 == 1;
        px[static_cast<size_t>(y * 8 + x)] = static_cast<uint8_t>(red ? 10 + p : blue ? 200 - p : 100 + p);
      }
    }
    storage::FrameRecord r;
    r.frame_id = static_cast<uint64_t>(k);
    r.slot = k;
    r.pattern = p;
    EXPECT_TRUE((*writer)->Append(r, px).ok());
  }
  EXPECT_TRUE((*writer)->Close().ok());
  return path;
}

TEST(TakeFramesTest, ACycleIsReadInPatternOrderAndDemosaiced) {
  const LightModel light = ShippedLight();
  const std::string path = WriteTake(light, "ok");
  auto cycle = LoadCycle(path, 1, light);
  ASSERT_TRUE(cycle.ok()) << cycle.status();
  ASSERT_EQ(cycle->raw.size(), 38u);
  EXPECT_EQ(cycle->camera_id, "hs-2");
  EXPECT_EQ(cycle->bits, 8);
  EXPECT_EQ(cycle->mosaic.Color(0, 0), 0);
  EXPECT_EQ(cycle->mosaic.Color(1, 0), 1);
  EXPECT_EQ(cycle->mosaic.Color(1, 1), 2);
  auto images = DemosaicCycle(*cycle, {.black_level_dn = 4});
  ASSERT_TRUE(images.ok()) << images.status();
  for (int p = 0; p < 38; ++p) {
    EXPECT_EQ(cycle->slots[static_cast<size_t>(p)], 38 + p);
    const float* v = (*images)[static_cast<size_t>(p)].at(3, 3);  // inside: every site's neighbours exist
    EXPECT_FLOAT_EQ(v[0], 10 + p - 4) << p;
    EXPECT_FLOAT_EQ(v[1], 100 + p - 4) << p;
    EXPECT_FLOAT_EQ(v[2], 200 - p - 4) << p;
  }
}

TEST(TakeFramesTest, ALostFrameOrAForeignPatternIsNamed) {
  const LightModel light = ShippedLight();
  auto lost = LoadCycle(WriteTake(light, "lost", /*skip=*/40), 1, light);
  ASSERT_FALSE(lost.ok());
  EXPECT_THAT(lost.status().message(), ::testing::HasSubstr("no image of pattern \"" + light.patterns[2].name));
  EXPECT_THAT(lost.status().message(), ::testing::HasSubstr("slot 40"));
  EXPECT_TRUE(LoadCycle(WriteTake(light, "lost2", /*skip=*/40), 0, light).ok());  // frame 0 is whole
  auto foreign = LoadCycle(WriteTake(light, "foreign", -1, "cross-sideways"), 0, light);
  ASSERT_FALSE(foreign.ok());
  EXPECT_THAT(foreign.status().message(), ::testing::HasSubstr("pattern 3 is \"cross-sideways\" in the file"));
}

}  // namespace
}  // namespace stage::processing
