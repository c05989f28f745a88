// The calibration board: OpenCV's own ChArUco detector, run on the simulated camera's rendered raw frame, finds the
// corners where the board's ground truth, projected through the camera model, says they are, to a fraction of a pixel
// once pixels are supersampled.
#include "stage/sim/board.h"

#include <algorithm>
#include <opencv2/aruco.hpp>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/imgproc.hpp>

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/sim/scene.h"

namespace stage::sim {
namespace {

v1::SimBoard DefaultBoard() {
  auto loaded = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.subject.kind=charuco"});
  EXPECT_TRUE(rig.ok()) << rig.status();
  return rig->rig.sim().subject().board();
}

TEST(BoardTest, CornersAreTheInnerGridCentredOnTheOrigin) {
  auto board = BoardModel::Create(DefaultBoard());
  ASSERT_TRUE(board.ok()) << board.status();
  const auto& corners = (*board)->corners();
  ASSERT_EQ(corners.size(), 10u * 8u);  // 11 x 9 squares
  Eigen::Vector3f mean = Eigen::Vector3f::Zero();
  for (const auto& c : corners) mean += c / static_cast<float>(corners.size());
  EXPECT_LT(mean.norm(), 1e-3f);
  // Corner ids run along rows: neighbours 30 mm apart.
  EXPECT_NEAR((corners[1] - corners[0]).norm(), 30, 1e-3);
  EXPECT_NEAR((corners[10] - corners[0]).norm(), 30, 1e-3);
  EXPECT_FLOAT_EQ((*board)->width_mm(), 330);
  // The print holds both inks in about equal measure (black squares plus marker bits against white squares).
  const auto& t = (*board)->texture();
  const double white = static_cast<double>(std::count(t.begin(), t.end(), 255)) / static_cast<double>(t.size());
  EXPECT_GT(white, 0.2);
  EXPECT_LT(white, 0.6);
  // A pose turns the corners about the board's centre.
  HeadPose pose;
  pose.rotation_deg = {90, 0, 0};
  pose.translation_mm = {0, 0, 10};
  const auto turned = (*board)->CornersAt(pose);
  EXPECT_NEAR(turned[0].x(), corners[0].z(), 1e-3);
  EXPECT_NEAR(turned[0].z(), -corners[0].x() + 10, 1e-3);
}

TEST(BoardTest, ErrorsNameTheField) {
  v1::SimBoard config = DefaultBoard();
  config.set_dictionary("DICT_9X9_1");
  auto bad = BoardModel::Create(config);
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("sim.subject.board.dictionary"), std::string::npos) << bad.status();
  config = DefaultBoard();
  config.set_dictionary("DICT_4X4_50");
  config.set_squares_x(12);
  config.set_squares_y(10);  // 60 markers
  bad = BoardModel::Create(config);
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("need 60 markers"), std::string::npos) << bad.status();
}

// Renders camera `id` under the cross full-on pattern in virtual frame `frame` and detects the ChArUco corners;
// returns the worst and the median distance from where the ground truth projects them, pixels, and how many.
struct Detection {
  int found = 0;
  double median_px = 0, worst_px = 0;
};
Detection DetectAndCompare(const std::shared_ptr<const SimScene>& scene, const std::string& id, int64_t frame) {
  const int index = scene->CameraIndex(id);
  CameraRenderer renderer(scene, index);
  const double exposure_s = 900e-6;
  const RawImage raw = renderer.Render(scene->PatternLevels(0), exposure_s, 1, frame);
  cv::Mat mosaic(raw.height, raw.width, CV_8U);
  for (size_t i = 0; i < raw.data.size(); ++i) mosaic.data[i] = static_cast<uint8_t>(raw.data[i] >> (raw.bits - 8));
  cv::Mat grey;
  cv::cvtColor(mosaic, grey, cv::COLOR_BayerBG2GRAY);  // PFNC BayerRG is OpenCV's BayerBG

  const v1::SimBoard& config = scene->rig().sim().subject().board();
  auto dictionary = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_5X5_100);
  auto board = cv::aruco::CharucoBoard::create(
      static_cast<int>(config.squares_x()), static_cast<int>(config.squares_y()),
      static_cast<float>(config.square_mm()), static_cast<float>(config.marker_mm()), dictionary);
  std::vector<std::vector<cv::Point2f>> marker_corners;
  std::vector<int> marker_ids;
  cv::aruco::detectMarkers(grey, dictionary, marker_corners, marker_ids);
  Detection out;
  if (marker_ids.empty()) return out;
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, grey, board, corners, ids);
  const auto truth = scene->board()->CornersAt(scene->PoseAt(frame));
  std::vector<double> errors;
  for (size_t k = 0; k < ids.size(); ++k) {
    Eigen::Vector2d expected;
    if (!scene->camera(index).Project(truth[static_cast<size_t>(ids[k])].cast<double>(), &expected)) continue;
    // OpenCV 4.6's ChArUco corners put the top-left pixel's corner, not its centre, at (0, 0) (opencv_contrib
    // #3024; OpenCV 4.13 changes it back, opencv #28380): half a pixel off the camera model's convention and
    // projectPoints'. Calibration code must mind it too.
    const Eigen::Vector2d found(corners[k].x - 0.5, corners[k].y - 0.5);
    errors.push_back((expected - found).norm());
  }
  out.found = static_cast<int>(errors.size());
  if (errors.empty()) return out;
  std::sort(errors.begin(), errors.end());
  out.median_px = errors[errors.size() / 2];
  out.worst_px = errors.back();
  return out;
}

TEST(BoardTest, OpenCvFindsTheCornersWhereTheGroundTruthSays) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.subject.kind=charuco", "sim.render_scale=0.25"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto scene = SimScene::FromLoadedRig(*rig);
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_TRUE((*scene)->animated());
  // Frame 0: square to +z; frame 6 (0.25 s): turned 30 degrees towards +x; seen by a front camera.
  for (int64_t frame : {0, 6}) {
    const Detection d = DetectAndCompare(*scene, "mv-05", frame);
    SCOPED_TRACE(frame);
    // Measured with the board's default texture sampling (4 x 4 rays a pixel for its print, one for the lighting):
    // median 0.12 px, worst 0.36 px over both frames (one ray a pixel for both: 0.38 and 0.90). OpenCV's own
    // refinement stops short of the corner (processing's RefineCorners takes it to 0.02 px). A wrong layout, a
    // mirrored board or a wrong square size would miss by pixels or not be found at all.
    EXPECT_GE(d.found, 66);  // of 80
    EXPECT_LT(d.median_px, 0.25);
    EXPECT_LT(d.worst_px, 0.6);
  }
}

}  // namespace
}  // namespace stage::sim
