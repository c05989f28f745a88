// The ChArUco calibration board: OpenCV's layout, printed into a texture, on a plate.
#include "stage/sim/board.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <opencv2/aruco.hpp>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <utility>

#include "absl/strings/str_cat.h"
#include "stage/common/aruco_dictionaries.h"

namespace stage::sim {
namespace {

constexpr float kThicknessMm = 3;

}  // namespace

absl::StatusOr<std::shared_ptr<const BoardModel>> BoardModel::Create(const v1::SimBoard& config) {
  const int dictionary_id = ArucoDictionaryId(config.dictionary());
  if (dictionary_id < 0) {
    return absl::InvalidArgumentError(absl::StrCat("sim.subject.board.dictionary: \"", config.dictionary(),
                                                   "\" is not an ArUco dictionary (", ArucoDictionaryNames(), ")"));
  }
  const int sx = static_cast<int>(config.squares_x()), sy = static_cast<int>(config.squares_y());
  const auto square = static_cast<float>(config.square_mm()), marker = static_cast<float>(config.marker_mm());
  cv::Ptr<cv::aruco::Dictionary> dictionary = cv::aruco::getPredefinedDictionary(dictionary_id);
  const int markers_needed = (sx * sy) / 2;
  if (markers_needed > dictionary->bytesList.rows) {
    return absl::InvalidArgumentError(absl::StrCat("sim.subject.board: ", sx, " x ", sy, " squares need ",
                                                   markers_needed, " markers; ", config.dictionary(), " has ",
                                                   dictionary->bytesList.rows));
  }
  cv::Ptr<cv::aruco::CharucoBoard> board = cv::aruco::CharucoBoard::create(sx, sy, square, marker, dictionary);

  std::shared_ptr<BoardModel> model(new BoardModel());
  model->width_mm_ = square * static_cast<float>(sx);
  model->height_mm_ = square * static_cast<float>(sy);
  const float w = model->width_mm_, h = model->height_mm_;
  // OpenCV's board frame (X, Y) to the stage: centred, facing +z, and not mirrored to a viewer in front, whichever way
  // OpenCV's Y runs (a marker's corners go clockwise on an image with y down).
  const auto& m0 = board->objPoints[0];
  const float turn = (m0[1].x - m0[0].x) * (m0[3].y - m0[0].y) - (m0[1].y - m0[0].y) * (m0[3].x - m0[0].x);
  const float y_sign = turn > 0 ? -1.0f : 1.0f;
  auto place = [&](float x, float y, float z) { return Eigen::Vector3f(x - w / 2, y_sign * (y - h / 2), z); };
  for (const cv::Point3f& c : board->chessboardCorners) model->corners_.push_back(place(c.x, c.y, 0));

  // The print, in board coordinates: row j is Y = (j + 0.5) / ppm, column i is X = (i + 0.5) / ppm.
  const auto ppm = static_cast<float>(config.pixels_per_mm());
  const int tw = std::max(2, static_cast<int>(std::lround(w * ppm))),
            th = std::max(2, static_cast<int>(std::lround(h * ppm)));
  cv::Mat print(th, tw, CV_8U, cv::Scalar(0));
  auto texel = [&](float mm) { return static_cast<int>(std::lround(mm * ppm)); };
  for (const auto& corners : board->objPoints) {  // the squares holding markers are white
    const cv::Point3f c = (corners[0] + corners[2]) * 0.5f;
    const int qx = static_cast<int>(c.x / square), qy = static_cast<int>(c.y / square);
    print(cv::Rect(cv::Point(texel(static_cast<float>(qx) * square), texel(static_cast<float>(qy) * square)),
                   cv::Point(texel(static_cast<float>(qx + 1) * square), texel(static_cast<float>(qy + 1) * square))))
        .setTo(255);
  }
  const int side = std::max(texel(marker), dictionary->markerSize + 2);
  for (size_t k = 0; k < board->objPoints.size(); ++k) {
    cv::Mat bits;
    cv::aruco::drawMarker(dictionary, board->ids[k], side, bits, 1);
    const auto s = static_cast<float>(side);
    const cv::Point2f from[4] = {{-0.5f, -0.5f}, {s - 0.5f, -0.5f}, {s - 0.5f, s - 0.5f}, {-0.5f, s - 0.5f}};
    cv::Point2f to[4];
    for (int c = 0; c < 4; ++c) to[c] = {board->objPoints[k][c].x * ppm - 0.5f, board->objPoints[k][c].y * ppm - 0.5f};
    cv::warpPerspective(bits, print, cv::getPerspectiveTransform(from, to), print.size(), cv::INTER_NEAREST,
                        cv::BORDER_TRANSPARENT);
  }
  model->texture_.assign(print.data, print.data + print.total());
  model->texture_width_ = tw;
  model->texture_height_ = th;

  // The plate: the printed face at z = 0 (part 0) and the back at z = -thickness (part 1); uv = (X / w, Y / h).
  TriangleMesh& mesh = model->neutral_;
  for (float z : {0.0f, -kThicknessMm}) {
    for (auto [x, y] : {std::pair{0.0f, 0.0f}, {w, 0.0f}, {w, h}, {0.0f, h}}) {
      mesh.positions.push_back(place(x, y, z));
      mesh.uvs.emplace_back(x / w, y / h);
    }
  }
  mesh.triangles = {{0, 1, 2}, {0, 2, 3}, {4, 6, 5}, {4, 7, 6}};
  mesh.parts = {0, 0, 1, 1};
  model->pivot_ = Eigen::Vector3f::Zero();
  return std::shared_ptr<const BoardModel>(std::move(model));
}

SurfaceSample BoardModel::Surface(const Eigen::Vector2f& uv, int part,
                                  const std::array<float, kExpressionCount>& /*expression*/) const {
  SurfaceSample s;
  s.material.specular = 0.02f;
  s.material.roughness = 0.5f;
  if (part != 0) {
    s.material.albedo = Eigen::Vector3f::Constant(0.3f);
    return s;
  }
  const float x =
      std::clamp(uv.x() * static_cast<float>(texture_width_) - 0.5f, 0.0f, static_cast<float>(texture_width_ - 1));
  const float y =
      std::clamp(uv.y() * static_cast<float>(texture_height_) - 0.5f, 0.0f, static_cast<float>(texture_height_ - 1));
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const int x1 = std::min(x0 + 1, texture_width_ - 1), y1 = std::min(y0 + 1, texture_height_ - 1);
  const float fx = x - static_cast<float>(x0), fy = y - static_cast<float>(y0);
  auto at = [&](int xx, int yy) {
    return static_cast<float>(texture_[static_cast<size_t>(yy) * static_cast<size_t>(texture_width_) + xx]) / 255;
  };
  const float t = (at(x0, y0) * (1 - fx) + at(x1, y0) * fx) * (1 - fy) + (at(x0, y1) * (1 - fx) + at(x1, y1) * fx) * fy;
  s.material.albedo = Eigen::Vector3f::Constant(kBlack + (kWhite - kBlack) * t);
  return s;
}

std::vector<Eigen::Vector3f> BoardModel::CornersAt(const HeadPose& pose) const {
  const Eigen::Matrix3f r = PoseRotation(pose);
  std::vector<Eigen::Vector3f> out;
  out.reserve(corners_.size());
  for (const auto& c : corners_) out.push_back(r * (c - pivot_) + pivot_ + pose.translation_mm);
  return out;
}

Performance BoardSequence() {
  Performance p;
  auto key = [&](double t, Eigen::Vector3f rot, Eigen::Vector3f shift = Eigen::Vector3f::Zero()) {
    HeadPose pose;
    pose.rotation_deg = rot;
    pose.translation_mm = shift;
    p.keys.emplace_back(t, pose);
  };
  // Every camera sees the printed face in several frames: first a turn to each side of the stage (rear-side cameras
  // sit 105 degrees round from +z), then tilts, shifts through the head's volume (depth too: a plate at one depth
  // leaves a camera's rotation and principal point trading off) and rolls.
  key(0.0, {0, 0, 0});
  key(0.25, {30, 0, 0});
  key(0.5, {-30, 0, 0}, {0, 0, 100});
  key(0.75, {80, 0, 15}, {0, 40, 0});
  key(1.0, {-80, 0, -15}, {0, -40, 0});
  key(1.25, {105, 15, 0}, {0, 0, -60});
  key(1.5, {-105, 15, 0}, {0, 0, -60});
  key(1.75, {55, 10, 0}, {-50, 0, 50});
  key(2.0, {-55, -10, 0}, {50, 0, 50});
  key(2.25, {0, 30, 0}, {0, 0, 100});
  key(2.5, {0, -30, 0}, {0, 0, -100});
  key(2.75, {20, 20, 30}, {80, 70, 60});
  key(3.0, {-20, -20, -30}, {-80, -70, -60});
  key(3.25, {100, -20, 30}, {30, 50, 60});
  key(3.5, {-100, -20, -30}, {-30, 50, 60});
  key(3.75, {70, 25, -40}, {0, -50, -80});
  key(4.0, {-70, 25, 40}, {0, -50, -80});
  key(4.25, {35, -35, 45}, {60, 0, 120});
  key(4.5, {-35, 35, -45}, {-60, 0, -120});
  key(4.75, {0, 0, 90});
  key(5.0, {0, 0, 0});
  return p;
}

}  // namespace stage::sim
