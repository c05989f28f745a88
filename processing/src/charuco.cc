// ChArUco detection: see charuco.h.
#include "charuco.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <opencv2/aruco.hpp>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "stage/common/aruco_dictionaries.h"
#include "statistics.h"

namespace stage::processing {
namespace {

cv::Ptr<cv::aruco::CharucoBoard> MakeBoard(const CharucoBoardSpec& spec) {
  return cv::aruco::CharucoBoard::create(spec.squares_x, spec.squares_y, static_cast<float>(spec.square_mm),
                                         static_cast<float>(spec.marker_mm),
                                         cv::aruco::getPredefinedDictionary(ArucoDictionaryId(spec.dictionary)));
}

// The linear image as 8 bits for the marker detector: its 99th percentile at 230.
cv::Mat EightBit(const Image& grey) {
  std::vector<float> sample;
  for (size_t i = 0; i < grey.pixels.size(); i += 7) sample.push_back(grey.pixels[i]);
  const float p99 = static_cast<float>(Quantile(std::move(sample), 99, 100));
  const float scale = !(p99 > 0) ? 1.0f : 230.0f / p99;
  cv::Mat out(grey.height, grey.width, CV_8U);
  for (size_t i = 0; i < grey.pixels.size(); ++i) {
    out.data[i] = static_cast<uint8_t>(std::clamp(grey.pixels[i] * scale + 0.5f, 0.0f, 255.0f));
  }
  return out;
}

// Each corner's chessboard square, pixels: the shortest distance to its neighbours on the grid that were found (the
// board's most foreshortened direction; the median over the view's corners for one without any).
std::vector<double> SquareSizesPx(const CharucoBoardSpec& spec, const std::vector<CornerObservation>& corners) {
  const int across = spec.squares_x - 1;  // corners along a row; ids run along rows
  std::map<int, Eigen::Vector2d> by_id;
  for (const CornerObservation& c : corners) by_id[c.id] = c.pixel;
  std::vector<double> out(corners.size(), 0);
  std::vector<double> all;
  for (size_t k = 0; k < corners.size(); ++k) {
    const int id = corners[k].id, col = id % across;
    std::vector<double> d;
    for (int n : {col > 0 ? id - 1 : -1, col + 1 < across ? id + 1 : -1, id - across, id + across}) {
      auto it = n >= 0 ? by_id.find(n) : by_id.end();
      if (it != by_id.end()) d.push_back((it->second - corners[k].pixel).norm());
    }
    if (d.empty()) continue;
    out[k] = *std::min_element(d.begin(), d.end());
    all.push_back(out[k]);
  }
  const double typical = Median(std::move(all));  // 0 for none
  for (double& v : out) {
    if (v == 0) v = typical;
  }
  return out;
}

}  // namespace

CharucoBoardSpec CharucoBoardSpec::FromRig(const v1::SimBoard& board) {
  CharucoBoardSpec s;
  if (board.has_squares_x()) s.squares_x = static_cast<int>(board.squares_x());
  if (board.has_squares_y()) s.squares_y = static_cast<int>(board.squares_y());
  if (board.has_square_mm()) s.square_mm = board.square_mm();
  if (board.has_marker_mm()) s.marker_mm = board.marker_mm();
  if (!board.dictionary().empty()) s.dictionary = board.dictionary();
  return s;
}

absl::Status CharucoBoardSpec::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError("board: " + what); };
  if (squares_x < 3 || squares_y < 3 || squares_x > 100 || squares_y > 100) {
    return bad(absl::StrCat("squares_x and squares_y must be in [3, 100], not ", squares_x, " x ", squares_y));
  }
  if (!(square_mm > 0) || !(marker_mm > 0) || !(marker_mm < square_mm)) {
    return bad(absl::StrCat("marker_mm (", marker_mm, ") must be > 0 and smaller than square_mm (", square_mm, ")"));
  }
  const int id = ArucoDictionaryId(dictionary);
  if (id < 0) {
    return bad(
        absl::StrCat("dictionary \"", dictionary, "\" is not an ArUco dictionary (", ArucoDictionaryNames(), ")"));
  }
  const int markers = squares_x * squares_y / 2;
  const int available = cv::aruco::getPredefinedDictionary(id)->bytesList.rows;
  if (markers > available) {
    return bad(absl::StrCat(squares_x, " x ", squares_y, " squares need ", markers, " markers; ", dictionary, " has ",
                            available));
  }
  return absl::OkStatus();
}

std::vector<Eigen::Vector3d> CharucoBoardSpec::Corners() const {
  std::vector<Eigen::Vector3d> out;
  const cv::Ptr<cv::aruco::CharucoBoard> board = MakeBoard(*this);  // alive while its corners are read
  for (const cv::Point3f& c : board->chessboardCorners) out.emplace_back(c.x, c.y, c.z);
  return out;
}

std::vector<CornerObservation> DetectCharuco(const Image& grey, const CharucoBoardSpec& spec, int min_corners) {
  const cv::Mat image = EightBit(grey);
  const cv::Ptr<cv::aruco::CharucoBoard> board = MakeBoard(spec);
  std::vector<std::vector<cv::Point2f>> marker_corners, rejected;
  std::vector<int> marker_ids;
  cv::aruco::detectMarkers(image, board->dictionary, marker_corners, marker_ids,
                           cv::aruco::DetectorParameters::create(), rejected);
  if (marker_ids.size() < 2) return {};
  // Markers the first pass missed, found where the board says they must be.
  cv::aruco::refineDetectedMarkers(image, board, marker_corners, marker_ids, rejected);
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, image, board, corners, ids);
  if (static_cast<int>(ids.size()) < min_corners) return {};
  std::vector<CornerObservation> out;
  out.reserve(ids.size());
  for (size_t k = 0; k < ids.size(); ++k) {
    // OpenCV 4.6's ChArUco corners put the top-left pixel's corner, not its centre, at (0, 0) (opencv_contrib #3024;
    // OpenCV 4.13 changes it back, opencv #28380): half a pixel off the camera model's convention.
    out.push_back({ids[k], Eigen::Vector2d(corners[k].x - 0.5, corners[k].y - 0.5)});
  }
  out = RefineCorners(grey, spec, std::move(out));
  if (static_cast<int>(out.size()) < min_corners) return {};
  return out;
}

std::vector<CornerObservation> RefineCorners(const Image& grey, const CharucoBoardSpec& spec,
                                             std::vector<CornerObservation> corners) {
  const cv::Mat image(grey.height, grey.width, CV_32F, const_cast<float*>(grey.pixels.data()));
  const std::vector<double> square = SquareSizesPx(spec, corners);
  const double margin_share = (spec.square_mm - spec.marker_mm) / 2 / spec.square_mm;
  std::vector<CornerObservation> out;
  out.reserve(corners.size());
  for (size_t k = 0; k < corners.size(); ++k) {
    // The plain chessboard about the corner reaches `margin` pixels along the edges; the window (2 win + 1 wide) and
    // the smoothing (about 2 sigma) stay inside it.
    // Near the image's edge the window shrinks to fit (the patch holds the window and the smoothing's reach).
    const double margin = square[k] * margin_share;
    const Eigen::Vector2d start = corners[k].pixel;
    const int cx = static_cast<int>(std::lround(start.x())), cy = static_cast<int>(std::lround(start.y()));
    const int room = std::min({cx, cy, image.cols - 1 - cx, image.rows - 1 - cy});
    int win = std::clamp(static_cast<int>(margin) - 1, 2, 16);
    auto sigma_of = [](int w) { return std::clamp(w / 3.5, 0.6, 4.0); };
    auto reach_of = [&](int w) { return w + static_cast<int>(std::ceil(3 * sigma_of(w))) + 3; };
    while (win > 2 && reach_of(win) > room) --win;
    const double sigma = sigma_of(win);
    const int reach = reach_of(win);
    if (reach > room) continue;  // too near the image's edge to refine
    const cv::Rect roi(cx - reach, cy - reach, 2 * reach + 1, 2 * reach + 1);
    cv::Mat patch;
    cv::GaussianBlur(image(roi), patch, cv::Size(0, 0), sigma);
    std::vector<cv::Point2f> p = {
        cv::Point2f(static_cast<float>(start.x() - roi.x), static_cast<float>(start.y() - roi.y))};
    cv::cornerSubPix(patch, p, cv::Size(win, win), cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 100, 1e-3));
    const Eigen::Vector2d refined(p[0].x + roi.x, p[0].y + roi.y);
    if ((refined - start).norm() > std::max(1.5, 0.5 * margin)) continue;  // lost: not a corner where it was found
    out.push_back({corners[k].id, refined});
  }
  return out;
}

}  // namespace stage::processing
