// Camera calibration from a calibration take: see calibrate.h.
#include "stage/processing/calibrate.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "calibrate_internal.h"
#include "charuco.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/status.h"
#include "stage/processing/calibration.h"
#include "stage/processing/light_model.h"
#include "stage/processing/take_frames.h"
#include "statistics.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;

// A camera of the job: its frames and what was found in them.
struct CameraInput {
  std::string id, path;
  const v1::CameraConfig* config = nullptr;
  CameraObservations observed;  // model: the rig's nominal at the images' size
  int64_t last_slot = -1;       // the highest slot its frame file stores
  int frames_read = 0;
};

cv::Matx33d K(const CameraModel& m) { return {m.fx(), 0, m.cx(), 0, m.fy(), m.cy(), 0, 0, 1}; }
cv::Mat Distortion(const CameraModel& m) {
  cv::Mat d(1, 5, CV_64F);
  for (int i = 0; i < 5; ++i) d.at<double>(i) = m.distortion()[static_cast<size_t>(i)];
  return d;
}

// solvePnP of `object` (any frame) seen at `pixels`: object -> camera. False when it fails.
bool Pnp(const std::vector<cv::Point3d>& object, const std::vector<cv::Point2d>& pixels, const CameraModel& m,
         Eigen::Isometry3d* pose, bool guess) {
  cv::Mat rvec = cv::Mat::zeros(3, 1, CV_64F), tvec = cv::Mat::zeros(3, 1, CV_64F);
  if (guess) {
    Eigen::AngleAxisd aa(pose->linear());
    for (int i = 0; i < 3; ++i) {
      rvec.at<double>(i) = aa.angle() * aa.axis()[i];
      tvec.at<double>(i) = pose->translation()[i];
    }
  }
  // A planar board without a guess: IPPE (OpenCV's iterative solver can run away on a plane seen obliquely).
  try {
    if (!cv::solvePnP(object, pixels, K(m), Distortion(m), rvec, tvec, guess,
                      guess ? cv::SOLVEPNP_ITERATIVE : cv::SOLVEPNP_IPPE)) {
      return false;
    }
  } catch (const cv::Exception&) {
    return false;  // degenerate corners (all on a line): this view gives no pose
  }
  cv::Mat r;
  cv::Rodrigues(rvec, r);
  Eigen::Matrix3d rot;
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) rot(a, b) = r.at<double>(a, b);
  }
  pose->linear() = rot;
  pose->translation() = Eigen::Vector3d(tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2));
  return std::isfinite(pose->translation().norm());
}

// The camera as an isometry: world -> camera.
Eigen::Isometry3d WorldToCamera(const CameraModel& m) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = m.rotation();
  t.translation() = -m.rotation() * m.position();
  return t;
}

// `m` with another pose. The rotation is orthonormalized first, so FromParameters's check cannot fail here.
CameraModel Placed(const CameraModel& m, const Eigen::Isometry3d& world_to_camera) {
  CameraParameters p = m.parameters();
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(world_to_camera.linear(), Eigen::ComputeFullU | Eigen::ComputeFullV);
  p.rotation = svd.matrixU() * svd.matrixV().transpose();
  p.position = -p.rotation.transpose() * world_to_camera.translation();
  return *CameraModel::FromParameters(p);
}

// Median reprojection error (pixels) of `corners` for a board at `board` (board -> world) seen by `m`.
double MedianError(const std::vector<Eigen::Vector3d>& board_corners, const std::vector<CornerObservation>& corners,
                   const CameraModel& m, const Eigen::Isometry3d& board) {
  std::vector<double> e;
  for (const CornerObservation& c : corners) {
    Eigen::Vector2d px;
    e.push_back(m.Project(board * board_corners[static_cast<size_t>(c.id)], &px) ? (px - c.pixel).norm() : 1e9);
  }
  return Median(std::move(e));
}

// The corners' points (through `board`: board -> world) and pixels, appended, as solvePnP takes them.
void AppendCorrespondences(const std::vector<Eigen::Vector3d>& board_corners,
                           const std::vector<CornerObservation>& corners, const Eigen::Isometry3d& board,
                           std::vector<cv::Point3d>* object, std::vector<cv::Point2d>* pixels) {
  for (const CornerObservation& c : corners) {
    const Eigen::Vector3d p = board * board_corners[static_cast<size_t>(c.id)];
    object->emplace_back(p.x(), p.y(), p.z());
    pixels->emplace_back(c.pixel.x(), c.pixel.y());
  }
}

// Every frame's board pose: of the poses each camera's view gives (through its model), the one the other views of
// the frame agree with best (the median of their median errors). A camera far off its model thus cannot pull the
// board with it.
BoardPoses InitialBoards(const std::vector<Eigen::Vector3d>& board_corners,
                         const std::vector<CameraObservations>& cameras) {
  std::map<int64_t, std::vector<std::pair<const CameraModel*, const std::vector<CornerObservation>*>>> by_frame;
  for (const CameraObservations& c : cameras) {
    for (const auto& [frame, corners] : c.frames) by_frame[frame].emplace_back(&c.model, &corners);
  }
  BoardPoses out;
  for (const auto& [frame, views] : by_frame) {
    double best = 1e300;
    for (const auto& [model, corners] : views) {
      std::vector<cv::Point3d> object;
      std::vector<cv::Point2d> pixels;
      AppendCorrespondences(board_corners, *corners, Eigen::Isometry3d::Identity(), &object, &pixels);
      Eigen::Isometry3d board_to_camera = Eigen::Isometry3d::Identity();
      if (!Pnp(object, pixels, *model, &board_to_camera, false)) continue;
      const Eigen::Isometry3d board = WorldToCamera(*model).inverse() * board_to_camera;
      std::vector<double> errors;
      for (const auto& [other, other_corners] : views) {
        errors.push_back(MedianError(board_corners, *other_corners, *other, board));
      }
      const double agreement = Median(std::move(errors));
      if (agreement < best) {
        best = agreement;
        out[frame] = board;
      }
    }
  }
  return out;
}

// Every camera placed by all the board's corners it saw, where the boards are (its intrinsics as they are): a camera
// centimetres off its model starts where it is.
void PlaceCameras(const std::vector<Eigen::Vector3d>& board_corners, const BoardPoses& boards,
                  std::vector<CameraObservations>* cameras) {
  for (CameraObservations& c : *cameras) {
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> pixels;
    for (const auto& [frame, corners] : c.frames) {
      const auto board = boards.find(frame);
      if (board != boards.end()) AppendCorrespondences(board_corners, corners, board->second, &object, &pixels);
    }
    if (object.size() < 6) continue;
    Eigen::Isometry3d pose = WorldToCamera(c.model);
    if (Pnp(object, pixels, c.model, &pose, true)) c.model = Placed(c.model, pose);
  }
}

// The rigid motion (no scale) that best maps `from` onto `to` (Kabsch).
Eigen::Isometry3d RigidFit(const std::vector<Eigen::Vector3d>& from, const std::vector<Eigen::Vector3d>& to) {
  Eigen::Matrix3Xd a(3, from.size()), b(3, to.size());
  for (size_t i = 0; i < from.size(); ++i) {
    a.col(static_cast<Eigen::Index>(i)) = from[i];
    b.col(static_cast<Eigen::Index>(i)) = to[i];
  }
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.matrix() = Eigen::umeyama(a, b, false);
  return t;
}

// `m` in a frame moved by `t` (old world -> new world).
CameraModel Moved(const CameraModel& m, const Eigen::Isometry3d& t) {
  return Placed(m, WorldToCamera(m) * t.inverse());
}

// The points of a 7 x 7 x 7 grid over a 300 mm cube round the stage origin (the head's volume) that `b` sees inside its
// image (a lens model says nothing outside, and its polynomial grows fast), with where `b` sees them.
struct SeenPoints {
  std::vector<Eigen::Vector3d> points;
  std::vector<Eigen::Vector2d> pixels;
};
SeenPoints SeenInVolume(const CameraModel& b) {
  SeenPoints out;
  for (int i = 0; i < 7; ++i) {
    for (int j = 0; j < 7; ++j) {
      for (int k = 0; k < 7; ++k) {
        const Eigen::Vector3d p(-150 + 50 * i, -150 + 50 * j, -150 + 50 * k);
        Eigen::Vector2d v;
        if (!b.Project(p, &v)) continue;
        if (v.x() < -0.5 || v.y() < -0.5 || v.x() > b.width() - 0.5 || v.y() > b.height() - 0.5) continue;
        out.points.push_back(p);
        out.pixels.push_back(v);
      }
    }
  }
  return out;
}

// RMS distance between where `a` sees `seen`'s points and where the camera they were seen by saw them, pixels.
double ProjectionDifference(const CameraModel& a, const SeenPoints& seen) {
  double sum2 = 0;
  int n = 0;
  for (size_t i = 0; i < seen.points.size(); ++i) {
    Eigen::Vector2d u;
    if (!a.Project(seen.points[i], &u)) continue;
    sum2 += (u - seen.pixels[i]).squaredNorm();
    ++n;
  }
  return n > 0 ? std::sqrt(sum2 / n) : 0;
}

// The rigid motion near `start` under which the calibrated cameras see the head's volume most nearly as the true ones
// do (least squares over every camera's seen points; Gauss-Newton with numeric derivatives). A calibration fixes its
// frame only up to a rigid motion; fitting the centres alone lets one poorly placed camera move the frame for all.
// `seen[c]`: SeenInVolume of calibrated camera c's truth.
Eigen::Isometry3d AlignByProjection(const std::vector<const CameraModel*>& calibrated,
                                    const std::vector<SeenPoints>& seen, Eigen::Isometry3d start) {
  auto residuals = [&](const Eigen::Isometry3d& align) {
    std::vector<double> r;
    for (size_t c = 0; c < calibrated.size(); ++c) {
      const CameraModel m = Moved(*calibrated[c], align);
      for (size_t i = 0; i < seen[c].points.size(); ++i) {
        Eigen::Vector2d u = seen[c].pixels[i];  // a point the moved camera cannot see adds nothing
        m.Project(seen[c].points[i], &u);
        r.push_back(u.x() - seen[c].pixels[i].x());
        r.push_back(u.y() - seen[c].pixels[i].y());
      }
    }
    return Eigen::Map<Eigen::VectorXd>(r.data(), static_cast<Eigen::Index>(r.size())).eval();
  };
  auto step = [](const Eigen::Isometry3d& a, const Eigen::Matrix<double, 6, 1>& d) {
    Eigen::Isometry3d delta = Eigen::Isometry3d::Identity();
    const double angle = d.head<3>().norm();
    if (angle > 0) delta.linear() = Eigen::AngleAxisd(angle, d.head<3>() / angle).toRotationMatrix();
    delta.translation() = d.tail<3>();
    return delta * a;
  };
  Eigen::Isometry3d align = start;
  Eigen::VectorXd r = residuals(align);
  for (int iteration = 0; iteration < 20; ++iteration) {
    Eigen::MatrixXd j(r.size(), 6);
    for (int k = 0; k < 6; ++k) {
      Eigen::Matrix<double, 6, 1> d = Eigen::Matrix<double, 6, 1>::Zero();
      d[k] = k < 3 ? 1e-7 : 1e-4;  // radians, mm
      j.col(k) = (residuals(step(align, d)) - r) / d[k];
    }
    const Eigen::Matrix<double, 6, 1> d = (j.transpose() * j).ldlt().solve(-j.transpose() * r);
    const Eigen::Isometry3d next = step(align, d);
    const Eigen::VectorXd next_r = residuals(next);
    if (!(next_r.squaredNorm() < r.squaredNorm())) break;
    align = next;
    r = next_r;
    if (d.head<3>().norm() < 1e-10 && d.tail<3>().norm() < 1e-7) break;
  }
  return align;
}

double AngleDeg(const Eigen::Matrix3d& r) { return Eigen::AngleAxisd(r).angle() * 180 / M_PI; }

// RMS over a grid of the image of the difference the two models' lens terms make, with `truth`'s focal lengths and
// principal point: sensor pixels.
double DistortionDifference(const CameraModel& calibrated, const CameraModel& truth) {
  CameraParameters p = truth.parameters();
  p.rotation = Eigen::Matrix3d::Identity();
  p.position = Eigen::Vector3d::Zero();
  CameraParameters q = p;
  q.distortion = calibrated.distortion();
  auto a = CameraModel::FromParameters(p), b = CameraModel::FromParameters(q);
  double sum2 = 0;
  int n = 0;
  for (int gy = 0; gy <= 8; ++gy) {
    for (int gx = 0; gx <= 8; ++gx) {
      const double x = (gx * (p.width - 1) / 8.0 - p.cx) / p.fx, y = (gy * (p.height - 1) / 8.0 - p.cy) / p.fy;
      Eigen::Vector2d u, v;
      a->Project({x, y, 1}, &u);
      b->Project({x, y, 1}, &v);
      sum2 += (u - v).squaredNorm();
      ++n;
    }
  }
  return std::sqrt(sum2 / n);
}

// The job's cameras with their frame files and nominal models at the images' size; cameras without a frame file go
// to `missing`.
absl::StatusOr<std::vector<CameraInput>> JobCameras(const CalibrationJob& job, const LoadedRig& rig,
                                                    CalibrationReport* report) {
  std::vector<std::string> ids = job.options.cameras;
  if (ids.empty()) {
    for (const v1::CameraConfig& c : rig.rig.cameras()) ids.push_back(c.id());
  }
  std::vector<CameraInput> out;
  for (const std::string& id : ids) {
    CameraInput c;
    c.id = id;
    for (const v1::CameraConfig& config : rig.rig.cameras()) {
      if (config.id() == id) c.config = &config;
    }
    if (c.config == nullptr) return absl::NotFoundError(absl::StrCat("camera \"", id, "\" is not in the take's rig"));
    c.path = job.take_dir + "/cameras/" + id + ".h5";
    if (!fs::exists(c.path)) {
      report->missing.emplace_back(id, "no frame file in the take");
      continue;
    }
    auto shape = ReadFrameFileShape(c.path);
    if (!shape.ok()) return shape.status();
    auto model = CameraAtImageSize(rig, id, shape->width, shape->height);
    if (!model.ok()) return model.status();
    c.observed.id = id;
    c.observed.model = *model;
    c.last_slot = shape->last_slot;
    out.push_back(std::move(c));
  }
  return out;
}

// Reads every camera's full-lit frames and finds the board in them.
absl::Status Detect(const CalibrationJob& job, const LightModel& light, const CharucoBoardSpec& board, int64_t first,
                    int64_t last, std::vector<CameraInput>* cameras,
                    const std::function<void(const JobProgress&)>& progress, const std::function<bool()>& cancelled) {
  JobProgress p{
      0, static_cast<int64_t>(cameras->size()) + 1,
      absl::StrCat("calibration: finding the board in ", cameras->size(), " camera(s), frames ", first, "-", last - 1)};
  if (progress) progress(p);
  for (CameraInput& c : *cameras) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(absl::StrCat("calibration of ", job.take_dir, " cancelled"));
    }
    auto visit = [&](int64_t frame, const Image& grey) -> absl::Status {
      ++c.frames_read;
      auto corners = DetectCharuco(grey, board, job.options.min_corners);
      if (!corners.empty()) c.observed.frames[frame] = std::move(corners);
      return absl::OkStatus();
    };
    STAGE_RETURN_IF_ERROR(
        ForEachFullLitFrame(c.path, first, last, light, c.config->photometric().black_level_dn(), visit));
    ++p.done;
    p.message = absl::StrFormat("%s: the board in %d of %d frame(s)", c.id, c.observed.frames.size(), c.frames_read);
    if (progress) progress(p);
  }
  return absl::OkStatus();
}

// Share of a 10 x 10 grid over the image with a corner in it.
double Coverage(const CameraObservations& o) {
  bool cell[10][10] = {};
  for (const auto& [frame, corners] : o.frames) {
    for (const CornerObservation& c : corners) {
      const int x = std::clamp(static_cast<int>(c.pixel.x() * 10 / o.model.width()), 0, 9);
      const int y = std::clamp(static_cast<int>(c.pixel.y() * 10 / o.model.height()), 0, 9);
      cell[y][x] = true;
    }
  }
  int n = 0;
  for (auto& row : cell) n += static_cast<int>(std::count(std::begin(row), std::end(row), true));
  return n / 100.0;
}

// The fit as a calibration file (whole sensors), and its figures into the report.
CameraCalibration Calibrated(const std::string& take_dir, const std::vector<CameraInput>& usable,
                             const BundleResult& fit, CalibrationReport* report) {
  CameraCalibration calibration;
  calibration.source = absl::StrCat("calibration take ", fs::path(take_dir).filename().string());
  for (size_t i = 0; i < usable.size(); ++i) {
    const CameraModel sensor = fit.cameras[i].Resized(static_cast<int>(usable[i].config->width()),
                                                      static_cast<int>(usable[i].config->height()));
    calibration.cameras.push_back({usable[i].id, sensor});
    const BundleCameraResult& r = fit.per_camera[i];
    const double scale = static_cast<double>(usable[i].observed.model.width()) / usable[i].config->width();
    report->image_scale = scale;  // the same for every camera of a take, up to each size's rounding
    report->cameras.push_back({usable[i].id, r.frames, r.corners_used, r.corners_dropped, r.rms_px, r.rms_px / scale,
                               Coverage(usable[i].observed)});
  }
  report->rms_px = fit.rms_px;
  report->iterations = fit.iterations;
  report->solver = fit.report;
  return calibration;
}

std::string TruthPath(const std::string& take_dir) { return take_dir + "/ground_truth/cameras.json"; }

// `calibration`, and the take rig's nominal models, against the take's truth.
absl::StatusOr<CalibrationEvaluation> EvaluateAgainstTruth(const std::string& take_dir, const LoadedRig& rig,
                                                           const CameraCalibration& calibration) {
  auto truth = ReadCameraCalibration(TruthPath(take_dir));
  if (!truth.ok()) return truth.status();
  auto nominal = NominalCalibration(rig);
  if (!nominal.ok()) return nominal.status();
  CalibrationEvaluation out;
  STAGE_ASSIGN_OR_RETURN(out.calibrated, CompareCalibrations(calibration, *truth));
  STAGE_ASSIGN_OR_RETURN(out.nominal, CompareCalibrations(*nominal, *truth));
  return out;
}

// The cameras that saw the board in `min_frames` frames or more; the others are named in the report, not dropped
// silently.
std::vector<CameraInput> Usable(std::vector<CameraInput> cameras, int min_frames, CalibrationReport* report) {
  std::vector<CameraInput> usable;
  for (CameraInput& c : cameras) {
    report->frames_read = std::max(report->frames_read, c.frames_read);
    if (static_cast<int>(c.observed.frames.size()) >= min_frames) {
      usable.push_back(std::move(c));
    } else {
      report->missing.emplace_back(
          c.id, c.observed.frames.empty() ? absl::StrCat("never saw the board in ", c.frames_read, " full-lit frame(s)")
                                          : absl::StrCat("saw the board in ", c.observed.frames.size(), " of ",
                                                         c.frames_read, " frame(s); ", min_frames, " needed"));
    }
  }
  return usable;
}

absl::Status WriteReport(const CalibrationReport& report) {
  return WriteFileAtomically(report.output_dir + "/report.json", CalibrationReportJson(report) + "\n");
}

}  // namespace

absl::StatusOr<BundleResult> SolveCalibration(const std::vector<Eigen::Vector3d>& board_corners,
                                              std::vector<CameraObservations> cameras, const BundleOptions& options) {
  std::vector<Eigen::Vector3d> nominal;
  for (const CameraObservations& c : cameras) nominal.push_back(c.model.position());
  BoardPoses boards = InitialBoards(board_corners, cameras);
  PlaceCameras(board_corners, boards, &cameras);
  boards = InitialBoards(board_corners, cameras);
  // A frame no view of which gave a pose (degenerate corners) is left out.
  for (CameraObservations& c : cameras) {
    for (auto it = c.frames.begin(); it != c.frames.end();) {
      it = boards.count(it->first) != 0 ? std::next(it) : c.frames.erase(it);
    }
    if (c.frames.empty()) {
      return absl::FailedPreconditionError(absl::StrCat("camera \"", c.id, "\": no view of the board gave a pose"));
    }
  }
  auto fit = BundleAdjust(board_corners, cameras, boards, options);
  if (!fit.ok()) return fit.status();
  // The stage frame: the rigid motion that best puts the calibrated centres on the nominal ones.
  if (cameras.size() >= 3) {
    std::vector<Eigen::Vector3d> from;
    for (const CameraModel& m : fit->cameras) from.push_back(m.position());
    const Eigen::Isometry3d to_stage = RigidFit(from, nominal);
    for (CameraModel& m : fit->cameras) m = Moved(m, to_stage);
    for (auto& [frame, pose] : fit->boards) pose = to_stage * pose;
  }
  return fit;
}

absl::StatusOr<CalibrationReport> RunCalibration(const CalibrationJob& job,
                                                 const std::function<void(const JobProgress&)>& progress,
                                                 const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(job.options.Validate());
  auto rig = LoadTakeRig(job.take_dir);
  if (!rig.ok()) return rig.status();
  auto light = LightModel::FromRig(*rig);
  if (!light.ok()) return light.status();
  const CharucoBoardSpec board = CharucoBoardSpec::FromRig(rig->rig.sim().subject().board());
  STAGE_RETURN_IF_ERROR(board.Validate());
  const std::vector<Eigen::Vector3d> corners = board.Corners();
  CalibrationReport report;
  report.take_dir = job.take_dir;
  report.output_dir = job.output_dir.empty() ? job.take_dir + "/derived/calibration" : job.output_dir;
  auto cameras = JobCameras(job, *rig, &report);
  if (!cameras.ok()) return cameras.status();
  // The frames: every whole cycle the cameras recorded.
  const int64_t cycle = static_cast<int64_t>(light->patterns.size());
  int64_t whole = 0;
  for (const CameraInput& c : *cameras) whole = std::max(whole, (c.last_slot + 1 + cycle - 1) / cycle);
  const int64_t first = job.options.first_frame;
  const int64_t last = job.options.last_frame < 0 ? whole : job.options.last_frame;
  if (last <= first) {
    return absl::InvalidArgumentError(absl::StrCat(job.take_dir, ": frames [", first, ", ", last, ") hold nothing"));
  }
  STAGE_RETURN_IF_ERROR(Detect(job, *light, board, first, last, &*cameras, progress, cancelled));

  // Progress counts the cameras read (as Detect did), then the fit as one more unit.
  const auto units = static_cast<int64_t>(cameras->size()) + 1;
  std::vector<CameraInput> usable = Usable(std::move(*cameras), job.options.min_frames, &report);
  if (usable.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat(job.take_dir, ": no camera saw the board in ", job.options.min_frames, " frame(s) or more"));
  }
  if (progress) {
    progress({units - 1, units, absl::StrCat("calibration: bundle adjustment of ", usable.size(), " camera(s)")});
  }
  std::vector<CameraObservations> observed;
  for (const CameraInput& c : usable) observed.push_back(c.observed);
  BundleOptions bundle;
  bundle.loss_px = job.options.loss_px;
  bundle.fit_k3 = job.options.fit_k3;
  auto fit = SolveCalibration(corners, observed, bundle);
  if (!fit.ok()) return absl::Status(fit.status().code(), absl::StrCat(job.take_dir, ": ", fit.status().message()));
  report.board_frames = static_cast<int>(fit->boards.size());
  const CameraCalibration calibration = Calibrated(job.take_dir, usable, *fit, &report);
  // On a simulated take, against the truth (and the nominal rig against it); an unreadable truth is an error.
  if (fs::exists(TruthPath(job.take_dir))) {
    STAGE_ASSIGN_OR_RETURN(const CalibrationEvaluation evaluation,
                           EvaluateAgainstTruth(job.take_dir, *rig, calibration));
    report.truth = evaluation.calibrated;
    report.nominal_truth = evaluation.nominal;
    report.has_truth = true;
  }
  std::error_code ec;
  fs::create_directories(report.output_dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(report.output_dir, ": ", ec.message()));
  STAGE_RETURN_IF_ERROR(WriteCameraCalibration(report.output_dir + "/cameras.json", calibration));
  STAGE_RETURN_IF_ERROR(WriteReport(report));
  if (progress) {
    progress(
        {units, units,
         absl::StrFormat("calibration: %d camera(s), reprojection RMS %.3f px", report.cameras.size(), report.rms_px)});
  }
  if (job.options.require_all && !report.missing.empty()) {
    std::vector<std::string> named;
    for (const auto& [id, why] : report.missing) named.push_back(absl::StrCat(id, " (", why, ")"));
    return absl::FailedPreconditionError(absl::StrCat(
        job.take_dir, ": ", report.missing.size(), " camera(s) not calibrated: ", absl::StrJoin(named, ", "),
        "; the other ", report.cameras.size(), " are in ", report.output_dir, "/cameras.json"));
  }
  return report;
}

std::string TruthComparisonJson(const TruthComparison& t) {
  nlohmann::ordered_json j;
  j["frame_offset_mm"] = t.frame_offset_mm;
  j["frame_rotation_deg"] = t.frame_rotation_deg;
  auto row = [](const CameraError& e) {
    return nlohmann::ordered_json{{"id", e.id},
                                  {"centre_mm", e.centre_mm},
                                  {"rotation_deg", e.rotation_deg},
                                  {"focal_percent", e.focal_percent},
                                  {"principal_px", e.principal_px},
                                  {"distortion_px", e.distortion_px},
                                  {"projection_px", e.projection_px}};
  };
  j["rms"] = row(t.rms);
  j["worst"] = row(t.worst);
  j["cameras"] = nlohmann::ordered_json::array();
  for (const CameraError& e : t.cameras) j["cameras"].push_back(row(e));
  return j.dump(2);
}

std::string FormatTruthComparison(const TruthComparison& t, const TruthComparison* nominal) {
  std::string out = absl::StrFormat(
      "Against the simulator's truth, in the frame where the cameras see the head's volume most nearly as the true "
      "ones\n"
      "do (moved %.3f mm, %.4f deg); sensor pixels:\n"
      "%-8s %10s %12s %10s %12s %13s %13s\n",
      t.frame_offset_mm, t.frame_rotation_deg, "camera", "centre mm", "rotation deg", "focal %", "principal px",
      "distortion px", "projection px");
  auto line = [&](const CameraError& e, const std::string& name) {
    absl::StrAppendFormat(&out, "%-8s %10.4f %12.5f %+10.4f %12.3f %13.3f %13.3f\n", name, e.centre_mm, e.rotation_deg,
                          e.focal_percent, e.principal_px, e.distortion_px, e.projection_px);
  };
  for (const CameraError& e : t.cameras) line(e, e.id);
  line(t.rms, "rms");
  line(t.worst, "worst");
  if (nominal != nullptr) {
    out += "The rig's nominal models against the same truth (what calibration is to beat):\n";
    line(nominal->rms, "rms");
    line(nominal->worst, "worst");
  }
  return out;
}

std::string CalibrationEvaluationJson(const CalibrationEvaluation& e) {
  nlohmann::ordered_json j;
  j["calibrated"] = nlohmann::ordered_json::parse(TruthComparisonJson(e.calibrated));
  j["nominal"] = nlohmann::ordered_json::parse(TruthComparisonJson(e.nominal));
  return j.dump(2);
}

std::string CalibrationReportJson(const CalibrationReport& r) {
  nlohmann::ordered_json j;
  j["stage"] = "calibration";
  j["take"] = fs::path(r.take_dir).filename().string();
  j["output"] = r.output_dir + "/cameras.json";
  j["image_scale"] = r.image_scale;
  j["frames_read"] = r.frames_read;
  j["board_frames"] = r.board_frames;
  j["rms_px"] = r.rms_px;
  j["iterations"] = r.iterations;
  j["solver"] = r.solver;
  j["cameras"] = nlohmann::ordered_json::array();
  for (const CameraCalibrationReport& c : r.cameras) {
    j["cameras"].push_back({{"id", c.id},
                            {"frames", c.frames},
                            {"corners_used", c.corners_used},
                            {"corners_dropped", c.corners_dropped},
                            {"rms_px", c.rms_px},
                            {"rms_sensor_px", c.rms_sensor_px},
                            {"coverage", c.coverage}});
  }
  j["missing"] = nlohmann::ordered_json::array();
  for (const auto& [id, why] : r.missing) j["missing"].push_back({{"id", id}, {"why", why}});
  if (r.has_truth) {
    j["truth"] = nlohmann::ordered_json::parse(TruthComparisonJson(r.truth));
    j["nominal_truth"] = nlohmann::ordered_json::parse(TruthComparisonJson(r.nominal_truth));
  }
  return j.dump(2);
}

std::string FormatCalibrationReport(const CalibrationReport& r) {
  std::string out = absl::StrFormat(
      "Calibration of %s: %d camera(s) from %d frame(s) with the board, reprojection RMS %.3f px (images at %.3g of "
      "the sensor), %d iterations\n%-8s %7s %8s %8s %9s %10s %9s\n",
      fs::path(r.take_dir).filename().string(), r.cameras.size(), r.board_frames, r.rms_px, r.image_scale, r.iterations,
      "camera", "frames", "corners", "dropped", "RMS px", "RMS sensor", "coverage");
  for (const CameraCalibrationReport& c : r.cameras) {
    absl::StrAppendFormat(&out, "%-8s %7d %8d %8d %9.3f %10.3f %8.0f%%\n", c.id, c.frames, c.corners_used,
                          c.corners_dropped, c.rms_px, c.rms_sensor_px, 100 * c.coverage);
  }
  for (const auto& [id, why] : r.missing) absl::StrAppendFormat(&out, "%-8s NOT CALIBRATED: %s\n", id, why);
  if (r.has_truth) out += FormatTruthComparison(r.truth, &r.nominal_truth);
  absl::StrAppend(&out, "Written: ", r.output_dir, "/cameras.json and report.json\n");
  return out;
}

absl::Status CalibrationOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError("calibration options: " + what); };
  if (first_frame < 0) return bad("first_frame must be >= 0");
  if (last_frame >= 0 && last_frame <= first_frame) return bad("the frame range is empty");
  if (min_corners < 6 || min_corners > 10000) return bad("min_corners must be in [6, 10000]");
  if (min_frames < 1) return bad("min_frames must be >= 1");
  if (!(loss_px > 0 && loss_px <= 100)) return bad("loss_px must be in (0, 100]");
  return absl::OkStatus();
}

absl::StatusOr<TruthComparison> CompareCalibrations(const CameraCalibration& calibrated,
                                                    const CameraCalibration& truth) {
  std::vector<const CalibratedCamera*> mine;
  std::vector<const CameraModel*> theirs;
  std::vector<Eigen::Vector3d> from, to;
  for (const CalibratedCamera& c : calibrated.cameras) {
    const CameraModel* t = truth.Find(c.id);
    if (t == nullptr) continue;
    mine.push_back(&c);
    theirs.push_back(t);
    from.push_back(c.model.position());
    to.push_back(t->position());
  }
  if (mine.size() < 3) {
    return absl::NotFoundError(absl::StrCat("the calibration (", calibrated.source, ") and the truth (", truth.source,
                                            ") share ", mine.size(), " camera(s); 3 are needed"));
  }
  std::vector<const CameraModel*> calibrated_models;
  for (const CalibratedCamera* c : mine) calibrated_models.push_back(&c->model);
  std::vector<SeenPoints> seen;
  for (const CameraModel* t : theirs) seen.push_back(SeenInVolume(*t));
  const Eigen::Isometry3d align = AlignByProjection(calibrated_models, seen, RigidFit(from, to));
  TruthComparison out;
  out.to_truth = align;
  out.frame_offset_mm = align.translation().norm();
  out.frame_rotation_deg = AngleDeg(align.linear());
  out.worst.id = "worst";
  for (size_t i = 0; i < mine.size(); ++i) {
    const CameraModel m = Moved(mine[i]->model, align);
    const CameraModel& t = *theirs[i];
    CameraError e;
    e.id = mine[i]->id;
    e.centre_mm = (m.position() - t.position()).norm();
    e.rotation_deg = AngleDeg(m.rotation() * t.rotation().transpose());
    e.focal_percent = 100 * ((m.fx() + m.fy()) / (t.fx() + t.fy()) - 1);
    e.principal_px = std::hypot(m.cx() - t.cx(), m.cy() - t.cy());
    e.distortion_px = DistortionDifference(m, t);
    e.projection_px = ProjectionDifference(m, seen[i]);
    out.cameras.push_back(e);
    for (auto [sum, value] : {std::pair{&out.rms.centre_mm, e.centre_mm},
                              {&out.rms.rotation_deg, e.rotation_deg},
                              {&out.rms.focal_percent, e.focal_percent},
                              {&out.rms.principal_px, e.principal_px},
                              {&out.rms.distortion_px, e.distortion_px},
                              {&out.rms.projection_px, e.projection_px}}) {
      *sum += value * value;
    }
    out.worst.centre_mm = std::max(out.worst.centre_mm, e.centre_mm);
    out.worst.rotation_deg = std::max(out.worst.rotation_deg, e.rotation_deg);
    if (std::abs(e.focal_percent) > std::abs(out.worst.focal_percent)) out.worst.focal_percent = e.focal_percent;
    out.worst.principal_px = std::max(out.worst.principal_px, e.principal_px);
    out.worst.distortion_px = std::max(out.worst.distortion_px, e.distortion_px);
    out.worst.projection_px = std::max(out.worst.projection_px, e.projection_px);
  }
  out.rms.id = "rms";
  for (double* v : {&out.rms.centre_mm, &out.rms.rotation_deg, &out.rms.focal_percent, &out.rms.principal_px,
                    &out.rms.distortion_px, &out.rms.projection_px}) {
    *v = std::sqrt(*v / static_cast<double>(out.cameras.size()));
  }
  return out;
}

absl::StatusOr<CameraCalibration> NominalCalibration(const LoadedRig& rig) {
  CameraCalibration out;
  out.source = "the rig's nominal models";
  for (const v1::CameraConfig& c : rig.rig.cameras()) {
    auto m = CameraModel::FromConfig(c, 1.0);
    if (!m.ok()) return m.status();
    out.cameras.push_back({c.id(), *std::move(m)});
  }
  return out;
}

absl::StatusOr<CalibrationEvaluation> EvaluateCalibration(const std::string& take_dir, const std::string& calibration) {
  auto calibrated = LoadJobCalibration(take_dir, calibration.empty() ? "derived/calibration" : calibration);
  if (!calibrated.ok()) return calibrated.status();
  auto rig = LoadTakeRig(take_dir);
  if (!rig.ok()) return rig.status();
  return EvaluateAgainstTruth(take_dir, *rig, **calibrated);
}

}  // namespace stage::processing
