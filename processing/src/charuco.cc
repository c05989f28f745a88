// ChArUco detection: see charuco.h.
#include "charuco.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <opencv2/aruco.hpp>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
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

// Each corner's square as the image shows it: the columns are the images of one square along the board's x and y, from
// the Jacobian at the corner of the homography that best maps the board's plane onto the view's corners (lens
// distortion bends it by well under a percent over a square). Empty when no homography fits.
std::vector<Eigen::Matrix2d> SquareFrames(const CharucoBoardSpec& spec, const std::vector<CornerObservation>& corners) {
  const std::vector<Eigen::Vector3d> board = spec.Corners();
  std::vector<cv::Point2d> from, to;
  for (const CornerObservation& c : corners) {
    from.emplace_back(board[static_cast<size_t>(c.id)].x(), board[static_cast<size_t>(c.id)].y());
    to.emplace_back(c.pixel.x(), c.pixel.y());
  }
  if (from.size() < 4) return {};
  const cv::Mat h = cv::findHomography(from, to, 0);
  if (h.empty()) return {};
  std::vector<Eigen::Matrix2d> out;
  out.reserve(corners.size());
  for (const cv::Point2d& b : from) {
    const double w = h.at<double>(2, 0) * b.x + h.at<double>(2, 1) * b.y + h.at<double>(2, 2);
    const double u = (h.at<double>(0, 0) * b.x + h.at<double>(0, 1) * b.y + h.at<double>(0, 2)) / w;
    const double v = (h.at<double>(1, 0) * b.x + h.at<double>(1, 1) * b.y + h.at<double>(1, 2)) / w;
    Eigen::Matrix2d j;  // d(u, v) / d(x, y)
    j << (h.at<double>(0, 0) - u * h.at<double>(2, 0)) / w, (h.at<double>(0, 1) - u * h.at<double>(2, 1)) / w,
        (h.at<double>(1, 0) - v * h.at<double>(2, 0)) / w, (h.at<double>(1, 1) - v * h.at<double>(2, 1)) / w;
    out.push_back(j * spec.square_mm);
  }
  return out;
}

// The largest disc about the corner inside the square's central region of half-side `share` squares, pixels: the
// region's nearer edge, with the square seen sheared as well as foreshortened.
double InscribedRadius(const Eigen::Matrix2d& frame, double share) {
  const double area = std::abs(frame.determinant());
  return share * area / std::max(frame.col(0).norm(), frame.col(1).norm());
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
  // Measured on the simulator's board (render scale 0.25; mv-04, mv-19 and mv-24 in 24 frames of the board's
  // performance; corners against the truth): where the board's edges meet at under 58 degrees (sine 0.85: a square
  // seen sheared), corners came 0.1-0.7 px off in the median and over 1 px at worst; at 58 degrees and more, 0.06-0.08
  // px with a 5 x 5 window, 0.05 with 7 x 7, 0.023 with 13 x 13.
  // The corners' error in the median goes as 1 / window: 0.14 px over the half-width (0.07 px at 5 x 5, 0.023 at 13 x
  // 13), each corner's sigma_px.
  constexpr double kSigmaTimesWindow = 0.14;
  constexpr int kMinWindow = 2;
  constexpr double kMinSine = 0.85;
  const std::vector<Eigen::Matrix2d> frames = SquareFrames(spec, corners);
  if (frames.size() != corners.size()) return {};
  // About a corner lie the plain chessboard (out to the markers, `margin_share` squares along each edge) and then the
  // markers' black borders (one of a marker's cells wide): alike in the four quadrants but for the point reflection
  // through the corner, whose pulls on the corner cancel. The markers' inner cells differ from marker to marker.
  const double margin_share = (spec.square_mm - spec.marker_mm) / 2 / spec.square_mm;
  const double symmetric_share =
      margin_share + spec.marker_mm / (MakeBoard(spec)->dictionary->markerSize + 2) / spec.square_mm;
  std::vector<CornerObservation> out;
  out.reserve(corners.size());
  for (size_t k = 0; k < corners.size(); ++k) {
    // The window (2 win + 1 wide) is sized to the plain chessboard about the corner (its nearest edge, `margin`
    // pixels away); the window's corners and the smoothing's reach (2 sigma) stay inside the symmetric region. A square
    // seen sheared or edge-on narrows both: the window shrinks, and a corner with no room for a 5 x 5 window, or whose
    // edges meet at too sharp an angle for their crossing to be found well, is dropped rather than pulled off. Near the
    // image's edge the window shrinks to fit (the patch holds the window and the smoothing's reach).
    const double margin = InscribedRadius(frames[k], margin_share);
    const double symmetric = InscribedRadius(frames[k], symmetric_share);
    const Eigen::Vector2d start = corners[k].pixel;
    const int cx = static_cast<int>(std::lround(start.x())), cy = static_cast<int>(std::lround(start.y()));
    const int room = std::min({cx, cy, image.cols - 1 - cx, image.rows - 1 - cy});
    const double sine = std::abs(frames[k].determinant()) / (frames[k].col(0).norm() * frames[k].col(1).norm());
    if (sine < kMinSine) continue;
    int win = std::clamp(static_cast<int>(margin) - 1, kMinWindow, 16);
    auto sigma_of = [](int w) { return std::clamp(w / 3.5, 0.6, 4.0); };
    auto reach_of = [&](int w) { return w + static_cast<int>(std::ceil(3 * sigma_of(w))) + 3; };
    auto fits = [&](int w) { return w * M_SQRT2 + 2 * sigma_of(w) <= symmetric; };
    while (win > kMinWindow && (reach_of(win) > room || !fits(win))) --win;
    if (!fits(win)) continue;
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
    out.push_back({corners[k].id, refined, kSigmaTimesWindow / win});
  }
  return out;
}

}  // namespace stage::processing
