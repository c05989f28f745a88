// A take rendered straight from the scene: the frame files hold each camera's full-on frames at the schedule's slots,
// the take file the rig, the ground truth the same frames; errors name what is wrong.
#include "stage/sim/rendered_take.h"

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/storage/frame_file.h"

namespace stage::sim {
namespace {

using ::testing::HasSubstr;

std::shared_ptr<const SimScene> Scene() {
  auto loaded = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(
      *loaded, {"sim.render_scale=0.04", "sim.subject.performance=range_of_motion", "sim.subject.head_resolution=64"});
  EXPECT_TRUE(rig.ok()) << rig.status();
  auto scene = SimScene::FromLoadedRig(*rig);
  EXPECT_TRUE(scene.ok()) << scene.status();
  return *scene;
}

TEST(RenderedTakeTest, EachCamerasFullOnFramesSitAtTheirSlotsBesideTheRigAndTheTruth) {
  auto scene = Scene();
  const std::string dir = ::testing::TempDir() + "/rendered-take";
  std::filesystem::remove_all(dir);
  int64_t calls = 0;
  RenderedTakeOptions options{
      .first_frame = 10, .last_frame = 16, .frame_step = 3, .cameras = {"mv-01", "mv-07"}, .uv_size = 64};
  options.progress = [&](int64_t done, int64_t total) {
    EXPECT_EQ(done, ++calls);
    EXPECT_EQ(total, 4);
  };
  ASSERT_TRUE(WriteRenderedTake(scene, dir, options).ok());
  EXPECT_EQ(calls, 4);
  std::ifstream take_file(dir + "/take.json");
  const nlohmann::json take = nlohmann::json::parse(take_file);
  EXPECT_EQ(take["state"], "rendered");
  EXPECT_EQ(take["rig"]["sim"]["subject"]["performance"], "range_of_motion");
  const int64_t cycle = scene->schedule().patterns_size();
  for (const char* id : {"mv-01", "mv-07"}) {
    auto file = storage::FrameFileReader::Open(dir + "/cameras/" + id + ".h5");
    ASSERT_TRUE(file.ok()) << file.status();
    EXPECT_EQ((*file)->info().camera_id, id);
    auto records = (*file)->Records();
    ASSERT_TRUE(records.ok());
    // Two frames (10 and 13), each its full-on pattern(s); the frame a slot falls in is the one rendered.
    ASSERT_GE(records->size(), 2u);
    ASSERT_EQ(records->size() % 2, 0u);
    const size_t per_frame = records->size() / 2;
    EXPECT_EQ((*records)[0].slot / cycle, 10);
    EXPECT_EQ((*records)[per_frame].slot / cycle, 13);
    for (const auto& r : *records) EXPECT_EQ(r.slot % cycle, r.pattern);
    // The subject fills part of the frame: some pixels lit well above the dark ones.
    auto pixels = (*file)->Pixels(0);
    ASSERT_TRUE(pixels.ok());
    const auto [lo, hi] = std::minmax_element(pixels->begin(), pixels->end());
    EXPECT_GT(*hi, *lo + 20) << id;
  }
  EXPECT_FALSE(std::filesystem::exists(dir + "/cameras/mv-02.h5"));
  for (const char* frame : {"/frame-000010", "/frame-000013"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/ground_truth" + frame + "/uv_position.exr")) << frame;
    EXPECT_FALSE(std::filesystem::exists(dir + "/ground_truth" + frame + "/mesh.obj")) << frame;
  }
  EXPECT_FALSE(std::filesystem::exists(dir + "/ground_truth/frame-000011"));

  auto again = WriteRenderedTake(scene, dir, options);
  EXPECT_THAT(again.message(), HasSubstr("holds a take already"));
  options.cameras = {"mv-99"};
  EXPECT_THAT(WriteRenderedTake(scene, dir + "-2", options).message(), HasSubstr("camera \"mv-99\" is not in the rig"));
}

// A renderer told the only exposures it will get (as a take of the full-on patterns tells it) renders them as one that
// computes every unit's responses, to a digital number where the float sums round apart; asked for another exposure,
// it renders that one right too (and from then on computes every unit's responses).
TEST(RenderedTakeTest, ARendererToldItsExposuresRendersThemAsBefore) {
  auto scene = Scene();
  const int camera = scene->CameraIndex("mv-05");
  ASSERT_GE(camera, 0);
  int full_on = -1, other = -1;
  for (int p = 0; p < scene->schedule().patterns_size(); ++p) {
    const EmitterLevels l = scene->PatternLevels(p);
    if (full_on < 0 && l.parallel.minCoeff() > 0.999f) full_on = p;
    if (other < 0 && l.parallel.minCoeff() < 0.5f && l.parallel.maxCoeff() > 0.5f) other = p;
  }
  ASSERT_GE(full_on, 0);
  ASSERT_GE(other, 0);
  const double exposure_s = scene->rig().cameras(camera).exposure_us() * 1e-6;
  CameraRenderer plain(scene, camera, 2), told(scene, camera, 2);
  told.ExpectOnly({scene->PatternLevels(full_on)});
  EXPECT_EQ(told.Responses(12)->diffuse.cols(), 1);
  auto compare = [&](int pattern, uint64_t counter) {
    const RawImage want = plain.Render(scene->PatternLevels(pattern), exposure_s, counter, 12);
    const RawImage got = told.Render(scene->PatternLevels(pattern), exposure_s, counter, 12);
    ASSERT_EQ(got.data.size(), want.data.size());
    int differ = 0, worst = 0, lit = 0;
    const int black = *std::min_element(want.data.begin(), want.data.end());
    for (size_t i = 0; i < want.data.size(); ++i) {
      const int d = std::abs(static_cast<int>(got.data[i]) - static_cast<int>(want.data[i]));
      differ += d != 0;
      worst = std::max(worst, d);
      lit += want.data[i] > black + 10;
    }
    EXPECT_LE(worst, 1) << "pattern " << pattern;
    EXPECT_LT(differ, static_cast<int>(want.data.size() / 1000) + 1) << "pattern " << pattern;
    EXPECT_GT(lit, 100) << "pattern " << pattern;
  };
  compare(full_on, 3);
  compare(other, 4);  // not among the exposures it was told of
  EXPECT_EQ(told.Responses(12)->basis, nullptr);
  EXPECT_EQ(told.Responses(12)->diffuse.cols(), static_cast<Eigen::Index>(scene->dome().units.size()));
}

}  // namespace
}  // namespace stage::sim
