#include "stage/processing/visual_hull.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "stage/common/camera_calibration.h"

namespace stage::processing {

namespace fs = std::filesystem;

std::vector<uint8_t> SilhouetteMask(const std::vector<float>& grey, int width, int height, float min_signal,
                                    int grow_px) {
  if (width <= 0 || height <= 0 || grey.size() != static_cast<size_t>(width) * height) return {};
  // A frame of background around the image, so that the flood from its corner reaches every border pixel.
  cv::Mat outside(height + 2, width + 2, CV_8U, cv::Scalar(0));
  for (int y = 0; y < height; ++y) {
    uint8_t* row = outside.ptr<uint8_t>(y + 1) + 1;
    const float* g = &grey[static_cast<size_t>(y) * width];
    for (int x = 0; x < width; ++x) row[x] = g[x] >= min_signal ? 255 : 0;
  }
  // The background the border reaches becomes 128; what is left at 0 is a hole in the subject.
  cv::floodFill(outside, cv::Point(0, 0), cv::Scalar(128), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  cv::Mat inside = outside(cv::Rect(1, 1, width, height)) != 128;
  if (grow_px > 0) {
    cv::dilate(inside, inside,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * grow_px + 1, 2 * grow_px + 1)));
  }
  std::vector<uint8_t> out(static_cast<size_t>(width) * height);
  for (int y = 0; y < height; ++y) {
    const uint8_t* row = inside.ptr<uint8_t>(y);
    for (int x = 0; x < width; ++x) out[static_cast<size_t>(y) * width + x] = row[x] ? 1 : 0;
  }
  return out;
}

absl::Status VisualHull::Write(const std::string& dir, const std::vector<Silhouette>& views) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return absl::InternalError(absl::StrCat(dir, ": cannot create: ", ec.message()));
  CameraCalibration cameras;
  cameras.source = "the silhouettes' views, at the masks' size";
  for (const Silhouette& s : views) {
    const int w = s.camera.width(), h = s.camera.height();
    if (s.inside.size() != static_cast<size_t>(w) * h) {
      return absl::InvalidArgumentError(
          absl::StrCat("silhouette \"", s.id, "\": ", s.inside.size(), " pixels, its camera ", w, "x", h));
    }
    cv::Mat png(h, w, CV_8U);
    for (size_t i = 0; i < s.inside.size(); ++i) png.data[i] = s.inside[i] ? 255 : 0;
    const std::string path = dir + "/" + s.id + ".png";
    if (!cv::imwrite(path, png)) return absl::InternalError(absl::StrCat(path, ": cannot write"));
    cameras.cameras.push_back({s.id, s.camera});
  }
  return WriteCameraCalibration(dir + "/cameras.json", cameras);
}

absl::StatusOr<VisualHull> VisualHull::Read(const std::string& dir) {
  auto cameras = ReadCameraCalibration(dir + "/cameras.json");
  if (!cameras.ok()) return cameras.status();
  std::vector<Silhouette> views;
  for (const CalibratedCamera& c : cameras->cameras) {
    const std::string path = dir + "/" + c.id + ".png";
    const cv::Mat png = cv::imread(path, cv::IMREAD_GRAYSCALE);
    if (png.empty()) return absl::NotFoundError(absl::StrCat(path, ": no silhouette (or not an image)"));
    if (png.cols != c.model.width() || png.rows != c.model.height()) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": ", png.cols, "x", png.rows, ", its camera in ", dir,
                                                     "/cameras.json ", c.model.width(), "x", c.model.height()));
    }
    Silhouette s{c.id, c.model, std::vector<uint8_t>(static_cast<size_t>(png.cols) * png.rows)};
    for (int y = 0; y < png.rows; ++y) {
      const uint8_t* row = png.ptr<uint8_t>(y);
      for (int x = 0; x < png.cols; ++x) s.inside[static_cast<size_t>(y) * png.cols + x] = row[x] >= 128;
    }
    views.push_back(std::move(s));
  }
  return VisualHull(std::move(views));
}

VisualHull::Seen VisualHull::Judge(const Eigen::Vector3d& p) const {
  Seen seen = Seen::kByNone;
  for (const Silhouette& s : views_) {
    const CameraModel& c = s.camera;
    const Eigen::Vector3d q = c.rotation() * (p - c.position());
    // Behind the view, or far outside its field (where the distortion's polynomial folds back): it does not see p.
    if (q.z() <= 0 || std::abs(q.x()) > 2 * c.width() / c.fx() * q.z() ||
        std::abs(q.y()) > 2 * c.height() / c.fy() * q.z()) {
      continue;
    }
    Eigen::Vector2d px;
    if (!c.Project(p, &px)) continue;
    const long x = std::lround(px.x()), y = std::lround(px.y());
    if (x < 0 || y < 0 || x >= c.width() || y >= c.height()) continue;
    if (!s.inside[static_cast<size_t>(y) * c.width() + static_cast<size_t>(x)]) return Seen::kOutside;
    seen = Seen::kInside;
  }
  return seen;
}

bool VisualHull::FirstSpan(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t0, double t1, double step,
                           double* in, double* out, bool* entered) const {
  if (!std::isfinite(t0) || !std::isfinite(t1) || !(t1 >= t0) || !(step > 0)) return false;
  auto outside = [&](double t) { return Judge(origin + t * dir) == Seen::kOutside; };
  // The boundary between `a` and `b`, one outside and the other not, to step / 32.
  auto boundary = [&](double a, double b) {
    const bool at_a = outside(a);
    for (int k = 0; k < 5; ++k) {
      const double m = 0.5 * (a + b);
      (outside(m) == at_a ? a : b) = m;
    }
    return 0.5 * (a + b);
  };
  // Runs of samples no view puts outside; the first that some view sees inside is the span (a run no view sees at all
  // is no evidence of the subject: the air beyond the views' images). A run is entered from outside when a sample
  // before it lies outside and its first sample is seen inside.
  const int64_t samples = static_cast<int64_t>(std::ceil((t1 - t0) / step));
  bool in_run = false, run_seen = false, from_outside = false;
  double previous = t0;
  for (int64_t k = 0; k <= samples; ++k) {
    const double t = std::min(t1, t0 + static_cast<double>(k) * step);
    const Seen at = Judge(origin + t * dir);
    if (at == Seen::kOutside) {
      if (in_run && run_seen) {
        *out = boundary(previous, t);
        if (entered != nullptr) *entered = from_outside;
        return true;
      }
      in_run = false;
    } else {
      if (!in_run) {
        in_run = true;
        run_seen = false;
        from_outside = k > 0 && at == Seen::kInside;
        *in = k == 0 ? t0 : boundary(previous, t);
      }
      run_seen |= at == Seen::kInside;
    }
    previous = t;
  }
  if (!(in_run && run_seen)) return false;
  *out = t1;
  if (entered != nullptr) *entered = from_outside;
  return true;
}

}  // namespace stage::processing
