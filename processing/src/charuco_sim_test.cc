// The calibration board as a machine-vision camera records it (12-bit Bayer, the simulator's sensor noise), found by
// the calibration's own detector on the demosaiced grey image: its corners land where the board's ground truth projects
// them, to a few hundredths of a pixel.
#include <algorithm>
#include <cstdio>
#include <map>
#include <memory>
#include <string>
#include <utility>

#include "absl/strings/str_cat.h"
#include "charuco.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/processing/photometric.h"
#include "stage/processing/take_frames.h"
#include "stage/sim/scene.h"

namespace stage::processing {
namespace {

struct Errors {
  size_t found = 0;
  double median_px = 0, worst_px = 0;
};

Errors Compare(const sim::SimScene& scene, int index, int64_t frame, const std::vector<CornerObservation>& found) {
  const auto truth = scene.board()->CornersAt(scene.PoseAt(frame));
  std::vector<double> errors;
  for (const CornerObservation& c : found) {
    Eigen::Vector2d expected;
    if (!scene.camera(index).Project(truth[static_cast<size_t>(c.id)].cast<double>(), &expected)) continue;
    errors.push_back((expected - c.pixel).norm());
  }
  Errors out;
  out.found = errors.size();
  if (errors.empty()) return out;
  std::sort(errors.begin(), errors.end());
  out.median_px = errors[errors.size() / 2];
  out.worst_px = errors.back();
  return out;
}

// The parallel full-on frame a camera records of the board in virtual frame `frame`, black level off, demosaiced by
// the stage's own bilinear demosaicing and averaged to grey: what calibration detects the board in.
Image RecordedGrey(const sim::SimScene& scene, sim::CameraRenderer* renderer, int pattern, int64_t frame) {
  const sim::RawImage raw = renderer->Render(scene.PatternLevels(pattern), 900e-6, 1, frame);
  const sim::SensorParams& sensor = scene.sensor(renderer->camera_index());
  Image mosaic(raw.width, raw.height, 1);
  for (size_t i = 0; i < raw.data.size(); ++i) {
    mosaic.pixels[i] = static_cast<float>(raw.data[i]) - static_cast<float>(sensor.black_level_dn);
  }
  Image rgb, grey(raw.width, raw.height, 1);
  DemosaicBilinear(mosaic.pixels.data(), raw.width, raw.height, Mosaic{}, &rgb);  // RGGB
  for (size_t i = 0; i < grey.pixels.size(); ++i) {
    grey.pixels[i] = (rgb.pixels[3 * i] + rgb.pixels[3 * i + 1] + rgb.pixels[3 * i + 2]) / 3;
  }
  return grey;
}

// The scene at a render scale (0.25 by default) with the board for subject (mv-05 recording 12 bits, mv-21 8 bits as
// the rig says), and the index of the pattern the machine-vision cameras record (parallel-full).
struct BoardScene {
  std::shared_ptr<const sim::SimScene> scene;
  CharucoBoardSpec spec;
  int parallel_full = -1;
};

absl::StatusOr<BoardScene> MakeBoardScene(const std::string& render_scale = "0.25") {
  auto builtin = LoadRig(kBuiltinRigName);
  if (!builtin.ok()) return builtin.status();
  auto loaded = ApplyRigOverrides(*builtin, {"sim.subject.kind=charuco", "sim.render_scale=" + render_scale});
  if (!loaded.ok()) return loaded.status();
  for (auto& c : *loaded->rig.mutable_cameras()) {
    if (c.id() == "mv-05") c.set_pixel_format(v1::PIXEL_FORMAT_BAYER_RG12);
  }
  BoardScene out;
  auto scene = sim::SimScene::FromLoadedRig(*loaded);
  if (!scene.ok()) return scene.status();
  out.scene = *scene;
  auto light = LightModel::FromRig(*loaded);
  if (!light.ok()) return light.status();
  for (size_t p = 0; p < light->patterns.size(); ++p) {
    if (light->patterns[p].name == "parallel-full") out.parallel_full = static_cast<int>(p);
  }
  if (out.parallel_full < 0) return absl::NotFoundError("no parallel-full pattern");
  out.spec = CharucoBoardSpec::FromRig(loaded->rig.sim().subject().board());
  return out;
}

TEST(CharucoSimTest, TheCornersOfTheRecordedBoardAreWhereTheTruthSays) {
  auto board = MakeBoardScene();
  ASSERT_TRUE(board.ok()) << board.status();
  const sim::SimScene& scene = *board->scene;
  // mv-05 in the middle ring, mv-21 in the top one (looking down 25 degrees: the board foreshortened). Frame 0: the
  // board square to +z; frame 6 (0.25 s): turned 30 degrees towards +x.
  for (const char* id : {"mv-05", "mv-21"}) {
    const int index = scene.CameraIndex(id);
    ASSERT_GE(index, 0);
    sim::CameraRenderer renderer(board->scene, index);
    for (int64_t frame : {0, 6}) {
      SCOPED_TRACE(absl::StrCat(id, " frame ", frame));
      const Image grey = RecordedGrey(scene, &renderer, board->parallel_full, frame);
      const Errors e = Compare(scene, index, frame, DetectCharuco(grey, board->spec));
      // Measured: median 0.024-0.031 px, worst 0.05-0.08 px (0.1 sensor pixels in the median). OpenCV's refinement
      // alone: 0.12 px; without the print's texture sampling (one ray a pixel): 0.3 px; demosaiced by OpenCV's
      // COLOR_BayerBG2GRAY instead, whose interpolation shifts with a pixel's place in the 2 x 2 tile: 0.09 px.
      std::printf("%s frame %d: %zu corners, median %.4f px, worst %.4f px\n", id, static_cast<int>(frame), e.found,
                  e.median_px, e.worst_px);
      EXPECT_GE(e.found, 66u);  // of 80
      EXPECT_LT(e.median_px, 0.04);
      EXPECT_LT(e.worst_px, 0.15);
    }
  }
}

TEST(CharucoSimTest, ABoardSeenShearedGivesNoCornersRatherThanBadOnes) {
  // mv-19 (top ring) in frames 32 and 36 of the board's performance sees the squares as rhombi whose edges meet at
  // about 45 degrees; a 5 x 5 window was all the plain chessboard about a corner allowed. Those corners came 0.35-0.63
  // px off in the median and 1.8-4 px at worst, the top ring's cameras fitted their corners 3-7 times worse than the
  // others, and their calibration was millimetres off. Frame 22, seen squarely, keeps its corners.
  auto board = MakeBoardScene();
  ASSERT_TRUE(board.ok()) << board.status();
  const sim::SimScene& scene = *board->scene;
  const int index = scene.CameraIndex("mv-19");
  ASSERT_GE(index, 0);
  sim::CameraRenderer renderer(board->scene, index);
  for (int64_t frame : {22, 32, 36}) {
    SCOPED_TRACE(absl::StrCat("mv-19 frame ", frame));
    const Image grey = RecordedGrey(scene, &renderer, board->parallel_full, frame);
    const Errors e = Compare(scene, index, frame, DetectCharuco(grey, board->spec));
    std::printf("mv-19 frame %d: %zu corners, median %.4f px, worst %.4f px\n", static_cast<int>(frame), e.found,
                e.median_px, e.worst_px);
    if (frame == 22) {
      EXPECT_GE(e.found, 66u);
    } else {
      EXPECT_LT(e.found, 30u);  // of 71-76 found before
    }
    if (e.found > 0) {
      EXPECT_LT(e.median_px, 0.08);
      EXPECT_LT(e.worst_px, 0.3);
    }
  }
}

// Not run by default (each frame renders 5.3 megapixels: about a minute on 2 cores): the corners as the cameras'
// whole sensors record them, for the full-scale figures in docs/geometry.md. Run with
// `stage_processing_sim_test --gtest_also_run_disabled_tests --gtest_filter=*FullScale*`.
TEST(CharucoSimTest, DISABLED_FullScaleCorners) {
  auto board = MakeBoardScene("1");
  ASSERT_TRUE(board.ok()) << board.status();
  const sim::SimScene& scene = *board->scene;
  const std::vector<std::pair<std::string, std::vector<int64_t>>> views = {
      {"mv-05", {0, 6}}, {"mv-19", {22, 38}}, {"mv-24", {16, 28}}};
  for (const auto& [id, frames] : views) {
    const int index = scene.CameraIndex(id);
    ASSERT_GE(index, 0);
    sim::CameraRenderer renderer(board->scene, index);
    for (int64_t frame : frames) {
      const Image grey = RecordedGrey(scene, &renderer, board->parallel_full, frame);
      const Errors e = Compare(scene, index, frame, DetectCharuco(grey, board->spec));
      std::printf("%s frame %d at full scale: %zu corners, median %.4f px, worst %.4f px\n", id.c_str(),
                  static_cast<int>(frame), e.found, e.median_px, e.worst_px);
      EXPECT_GE(e.found, 40u);
    }
  }
}

}  // namespace
}  // namespace stage::processing
