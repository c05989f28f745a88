// Bundle adjustment: see bundle_adjustment.h.
#include "bundle_adjustment.h"

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace stage::processing {
namespace {

// Intrinsics block: fx, fy, cx, cy, k1, k2, p1, p2, k3 (CameraModel's distortion order).
constexpr int kIntrinsics = 9;

// The weight of a corner whose expected error is not known: that of a corner refined in a 9 x 9 window.
constexpr double kUnknownCornerSigmaPx = 0.035;

// A corner seen by a camera in a frame: residual = the model's projection (CameraModel::Project) - the detection.
struct CornerResidual {
  CornerResidual(const Eigen::Vector3d& corner, const Eigen::Vector2d& pixel) : corner_(corner), pixel_(pixel) {}

  // camera: angle-axis (world -> camera) and centre; k: intrinsics; board: angle-axis and translation (board -> world).
  template <typename T>
  bool operator()(const T* camera, const T* k, const T* board, T* residual) const {
    const T p[3] = {T(corner_.x()), T(corner_.y()), T(corner_.z())};
    T world[3];
    ceres::AngleAxisRotatePoint(board, p, world);
    for (int i = 0; i < 3; ++i) world[i] = world[i] + board[3 + i] - camera[3 + i];
    T c[3];
    ceres::AngleAxisRotatePoint(camera, world, c);
    const T x = c[0] / c[2], y = c[1] / c[2];
    const T r2 = x * x + y * y;
    const T radial = T(1) + k[4] * r2 + k[5] * r2 * r2 + k[8] * r2 * r2 * r2;
    const T xd = x * radial + T(2) * k[6] * x * y + k[7] * (r2 + T(2) * x * x);
    const T yd = y * radial + k[6] * (r2 + T(2) * y * y) + T(2) * k[7] * x * y;
    residual[0] = k[0] * xd + k[2] - T(pixel_.x());
    residual[1] = k[1] * yd + k[3] - T(pixel_.y());
    return true;
  }

  Eigen::Vector3d corner_;
  Eigen::Vector2d pixel_;
};

struct Parameters {
  std::vector<std::array<double, 6>> poses;
  std::vector<std::array<double, kIntrinsics>> intrinsics;
  std::map<int64_t, std::array<double, 6>> boards;
};

Parameters Pack(const std::vector<CameraObservations>& cameras, const BoardPoses& boards) {
  Parameters p;
  for (const CameraObservations& c : cameras) {
    const CameraParameters m = c.model.parameters();
    Eigen::AngleAxisd aa(m.rotation);
    const Eigen::Vector3d r = aa.angle() * aa.axis();
    p.poses.push_back({r.x(), r.y(), r.z(), m.position.x(), m.position.y(), m.position.z()});
    p.intrinsics.push_back(
        {m.fx, m.fy, m.cx, m.cy, m.distortion[0], m.distortion[1], m.distortion[2], m.distortion[3], m.distortion[4]});
  }
  for (const auto& [frame, pose] : boards) {
    Eigen::AngleAxisd aa(pose.rotation());
    const Eigen::Vector3d r = aa.angle() * aa.axis();
    const Eigen::Vector3d t = pose.translation();
    p.boards[frame] = {r.x(), r.y(), r.z(), t.x(), t.y(), t.z()};
  }
  return p;
}

Eigen::Matrix3d Rotation(const double* angle_axis) {
  const Eigen::Vector3d r(angle_axis[0], angle_axis[1], angle_axis[2]);
  const double angle = r.norm();
  return angle > 0 ? Eigen::AngleAxisd(angle, r / angle).toRotationMatrix() : Eigen::Matrix3d::Identity();
}

// One fit over the observations `use` keeps; returns Ceres's summary.
ceres::Solver::Summary Fit(const std::vector<Eigen::Vector3d>& board_corners,
                           const std::vector<CameraObservations>& cameras,
                           const std::vector<std::map<int64_t, std::vector<bool>>>& use, const BundleOptions& options,
                           int64_t fixed_frame, Parameters* p) {
  ceres::Problem problem;
  for (size_t i = 0; i < cameras.size(); ++i) {
    for (const auto& [frame, corners] : cameras[i].frames) {
      const std::vector<bool>& keep = use[i].at(frame);
      for (size_t k = 0; k < corners.size(); ++k) {
        if (!keep[k]) continue;
        auto* cost = new ceres::AutoDiffCostFunction<CornerResidual, 2, 6, kIntrinsics, 6>(
            new CornerResidual(board_corners[static_cast<size_t>(corners[k].id)], corners[k].pixel));
        // Each corner weighs by its expected error (1 / sigma^2; the scale is arbitrary: every residual is a corner's):
        // at render scale 0.25 the weights took the cameras' centres from 0.12 to 0.087 mm RMS.
        const double sigma = corners[k].sigma_px > 0 ? corners[k].sigma_px : kUnknownCornerSigmaPx;
        const double weight = std::pow(kUnknownCornerSigmaPx / sigma, 2);
        problem.AddResidualBlock(
            cost, new ceres::ScaledLoss(new ceres::HuberLoss(options.loss_px), weight, ceres::TAKE_OWNERSHIP),
            p->poses[i].data(), p->intrinsics[i].data(), p->boards.at(frame).data());
      }
    }
    if (!options.fit_k3 && problem.HasParameterBlock(p->intrinsics[i].data())) {
      problem.SetManifold(p->intrinsics[i].data(), new ceres::SubsetManifold(kIntrinsics, {8}));
    }
  }
  if (problem.HasParameterBlock(p->boards.at(fixed_frame).data())) {
    problem.SetParameterBlockConstant(p->boards.at(fixed_frame).data());
  }
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::DENSE_SCHUR;
  solver.max_num_iterations = options.max_iterations;
  // One thread: Ceres's threads sum in an order that varies from run to run, and the calibration would differ in its
  // last digits between runs (the fit takes seconds).
  solver.num_threads = 1;
  solver.function_tolerance = 1e-12;
  solver.parameter_tolerance = 1e-12;
  solver.gradient_tolerance = 1e-14;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);
  return summary;
}

}  // namespace

absl::StatusOr<BundleResult> BundleAdjust(const std::vector<Eigen::Vector3d>& board_corners,
                                          const std::vector<CameraObservations>& cameras, const BoardPoses& boards,
                                          const BundleOptions& options) {
  if (cameras.empty() || boards.empty()) return absl::InvalidArgumentError("bundle adjustment: nothing to fit");
  std::vector<std::map<int64_t, std::vector<bool>>> use(cameras.size());
  for (size_t i = 0; i < cameras.size(); ++i) {
    if (cameras[i].frames.empty()) {
      return absl::InvalidArgumentError(absl::StrCat("bundle adjustment: camera \"", cameras[i].id, "\" saw nothing"));
    }
    for (const auto& [frame, corners] : cameras[i].frames) {
      if (boards.count(frame) == 0) {
        return absl::InvalidArgumentError(absl::StrCat("bundle adjustment: no board pose for frame ", frame));
      }
      for (const CornerObservation& c : corners) {
        if (c.id < 0 || c.id >= static_cast<int>(board_corners.size())) {
          return absl::InvalidArgumentError(
              absl::StrCat("bundle adjustment: corner id ", c.id, " is not on the board"));
        }
      }
      use[i][frame].assign(corners.size(), true);
    }
  }
  const int64_t fixed = options.fixed_frame >= 0 ? options.fixed_frame : boards.begin()->first;
  if (boards.count(fixed) == 0) return absl::InvalidArgumentError(absl::StrCat("no board pose for frame ", fixed));
  Parameters p = Pack(cameras, boards);
  BundleResult result;
  result.per_camera.resize(cameras.size());
  ceres::Solver::Summary summary;
  for (int pass = 0; pass < 2; ++pass) {
    // The held board: the one asked for, or (when outliers took all its corners) the first frame still seen.
    int64_t held = -1;
    for (size_t i = 0; i < cameras.size() && held != fixed; ++i) {
      for (const auto& [frame, keep] : use[i]) {
        if (std::find(keep.begin(), keep.end(), true) == keep.end()) continue;
        if (frame == fixed || held < 0 || frame < held) held = frame;
      }
    }
    summary = Fit(board_corners, cameras, use, options, held, &p);
    result.iterations += static_cast<int>(summary.iterations.size());
    if (summary.termination_type != ceres::CONVERGENCE) {
      return absl::FailedPreconditionError(absl::StrCat("bundle adjustment did not converge: ", summary.BriefReport()));
    }
    // Residuals per corner, then the outliers dropped for the second pass.
    double total2 = 0;
    int64_t total_n = 0;
    for (size_t i = 0; i < cameras.size(); ++i) {
      std::vector<std::pair<std::vector<bool>*, std::vector<double>>> errors;
      double sum2 = 0;
      int n = 0;
      for (const auto& [frame, corners] : cameras[i].frames) {
        std::vector<double> e(corners.size(), 0);
        for (size_t k = 0; k < corners.size(); ++k) {
          CornerResidual r(board_corners[static_cast<size_t>(corners[k].id)], corners[k].pixel);
          double res[2];
          r(p.poses[i].data(), p.intrinsics[i].data(), p.boards.at(frame).data(), res);
          e[k] = std::hypot(res[0], res[1]);
          if (use[i][frame][k]) {
            sum2 += e[k] * e[k];
            ++n;
          }
        }
        errors.emplace_back(&use[i][frame], std::move(e));
      }
      const double rms = n > 0 ? std::sqrt(sum2 / n) : 0;
      BundleCameraResult& out = result.per_camera[i];
      out = {rms, n, 0, static_cast<int>(cameras[i].frames.size())};
      for (auto& [keep, e] : errors) {
        for (size_t k = 0; k < e.size(); ++k) {
          if (pass == 0) (*keep)[k] = e[k] <= std::max(0.5, options.outlier_factor * rms);
          out.corners_dropped += !(*keep)[k];
        }
      }
      total2 += sum2;
      total_n += n;
    }
    result.rms_px = total_n > 0 ? std::sqrt(total2 / static_cast<double>(total_n)) : 0;
  }
  for (size_t i = 0; i < cameras.size(); ++i) {
    CameraParameters m = cameras[i].model.parameters();
    m.rotation = Rotation(p.poses[i].data());
    m.position = {p.poses[i][3], p.poses[i][4], p.poses[i][5]};
    const auto& k = p.intrinsics[i];
    m.fx = k[0];
    m.fy = k[1];
    m.cx = k[2];
    m.cy = k[3];
    m.distortion = {k[4], k[5], k[6], k[7], k[8]};
    auto model = CameraModel::FromParameters(m);
    if (!model.ok()) {
      return absl::FailedPreconditionError(absl::StrCat("bundle adjustment: camera \"", cameras[i].id,
                                                        "\" came out unusable: ", model.status().message()));
    }
    result.cameras.push_back(*model);
  }
  for (const auto& [frame, b] : p.boards) {
    Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
    pose.linear() = Rotation(b.data());
    pose.translation() = Eigen::Vector3d(b[3], b[4], b[5]);
    result.boards[frame] = pose;
  }
  result.report = summary.BriefReport();
  return result;
}

}  // namespace stage::processing
