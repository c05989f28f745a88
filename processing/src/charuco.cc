// ChArUco detection: see charuco.h.
#include "charuco.h"

#include <opencv2/aruco.hpp>
#include <opencv2/aruco/charuco.hpp>

#include "absl/strings/str_cat.h"
#include "stage/common/aruco_dictionaries.h"

namespace stage::processing {
namespace {

cv::Ptr<cv::aruco::CharucoBoard> MakeBoard(const CharucoBoardSpec& spec) {
  return cv::aruco::CharucoBoard::create(spec.squares_x, spec.squares_y, static_cast<float>(spec.square_mm),
                                         static_cast<float>(spec.marker_mm),
                                         cv::aruco::getPredefinedDictionary(ArucoDictionaryId(spec.dictionary)));
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
    return bad(absl::StrCat("dictionary \"", dictionary, "\" is not an ArUco dictionary (", ArucoDictionaryNames(),
                            ")"));
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

std::vector<CornerObservation> DetectCharuco(const std::vector<uint8_t>& grey, int width, int height,
                                             const CharucoBoardSpec& spec, int min_corners) {
  const cv::Mat image(height, width, CV_8U, const_cast<uint8_t*>(grey.data()));
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
  return out;
}

}  // namespace stage::processing
