// Multi-view stereo speed on one frame of a recorded take (issue #27: depth + fusion + mesh <= 30 s a frame on 2
// cores at half resolution, <= 2 min at full), beside baselines measured in the same run on the same views:
//  - reading the 24 full-lit images from their frame files (HDF5, demosaiced to grey) and undistorting them;
//  - OpenCV's plain semi-global block matching (StereoSGBM, 5 x 5 blocks, MODE_SGBM) on the same pairs: every view
//    with its nearest neighbour beside it on its ring, rectified (stereoRectify, remap), over the disparities of the
//    head's volume;
//  - the reconstruction on 1 thread and on 2 (how it scales with cores).
// Run: build/bin/mvs_bench --take TAKE [--calibration ground_truth] [--frame 0] [--image-scale 1]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "CLI/CLI.hpp"
#include "mvs_internal.h"
#include "stage/processing/mvs.h"

namespace {

using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

[[noreturn]] void Die(const absl::Status& s) {
  std::fprintf(stderr, "mvs_bench: %s\n", std::string(s.message()).c_str());
  std::exit(1);
}

using stage::processing::MvsView;

// The views of `frame` as RunMvs reads them.
std::vector<MvsView> ReadViews(const std::string& take_dir, const std::string& calibration, int64_t frame,
                               double scale) {
  stage::processing::MvsJob job;
  job.take_dir = take_dir;
  job.calibration = calibration;
  auto take = stage::processing::OpenMvsTake(job);
  if (!take.ok()) Die(take.status());
  stage::processing::FrameViews in;
  if (auto s = stage::processing::ReadFrameViews(*take, frame, scale, &in); !s.ok()) Die(s);
  return std::move(in.views);
}

cv::Matx33d K(const MvsView& v) { return cv::Matx33d(v.fx, 0, v.cx, 0, v.fy, v.cy, 0, 0, 1); }

// OpenCV's SGBM on the pair (a, b), rectified; returns the pixels with a disparity.
int64_t Sgbm(const MvsView& a, const MvsView& b, double volume_radius_mm) {
  // b's pose relative to a: x_b = R x_a + T.
  Eigen::Matrix3d r = b.rotation * a.rotation.transpose();
  Eigen::Vector3d t = b.rotation * (a.position - b.position);
  cv::Matx33d rcv;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) rcv(i, j) = r(i, j);
  }
  const cv::Vec3d tcv(t.x(), t.y(), t.z());
  cv::Mat r1, r2, p1, p2, q;
  const cv::Size size(a.width, a.height);
  cv::stereoRectify(K(a), cv::noArray(), K(b), cv::noArray(), size, rcv, tcv, r1, r2, p1, p2, q, 0, -1);
  // The cameras converge on the head: each rectified image's principal point is moved so that the stage origin sits
  // in its middle (the disparities then run about 0, and both views of the head stay in the image).
  auto centre_on_origin = [&](const MvsView& v, const cv::Mat& rect, cv::Mat& p) {
    const Eigen::Vector3d c = v.rotation * (-v.position);
    const cv::Mat x = rect * (cv::Mat_<double>(3, 1) << c.x(), c.y(), c.z());
    p.at<double>(0, 2) = v.width / 2.0 - p.at<double>(0, 0) * x.at<double>(0) / x.at<double>(2);
    p.at<double>(1, 2) = v.height / 2.0 - p.at<double>(1, 1) * x.at<double>(1) / x.at<double>(2);
  };
  centre_on_origin(a, r1, p1);
  centre_on_origin(b, r2, p2);
  p2.at<double>(1, 2) = p1.at<double>(1, 2);  // rows stay aligned
  cv::Mat m1x, m1y, m2x, m2y, ra, rb;
  cv::initUndistortRectifyMap(K(a), cv::noArray(), r1, p1, size, CV_32FC1, m1x, m1y);
  cv::initUndistortRectifyMap(K(b), cv::noArray(), r2, p2, size, CV_32FC1, m2x, m2y);
  const cv::Mat ga(a.height, a.width, CV_32F, const_cast<float*>(a.grey.data()));
  const cv::Mat gb(b.height, b.width, CV_32F, const_cast<float*>(b.grey.data()));
  double hi = 0;
  cv::minMaxLoc(ga, nullptr, &hi);
  cv::Mat a8, b8;
  ga.convertTo(a8, CV_8U, 255 / std::max(hi, 1e-6));
  gb.convertTo(b8, CV_8U, 255 / std::max(hi, 1e-6));
  cv::remap(a8, ra, m1x, m1y, cv::INTER_LINEAR);
  cv::remap(b8, rb, m2x, m2y, cv::INTER_LINEAR);
  // Disparities about the origin's (0) over the head's volume: f B r / z^2, with a margin.
  const double f = p1.at<double>(0, 0), baseline = cv::norm(tcv), z = a.position.norm();
  const int reach = static_cast<int>(std::ceil(1.5 * f * baseline * volume_radius_mm / (z * z))) + 8;
  const int min_d = -reach, num = ((2 * reach + 15) / 16) * 16;
  auto sgbm = cv::StereoSGBM::create(min_d, num, 5, 8 * 25, 32 * 25, 1, 0, 10, 100, 2, cv::StereoSGBM::MODE_SGBM);
  cv::Mat disparity;
  sgbm->compute(ra, rb, disparity);
  if (std::getenv("MVS_BENCH_DEBUG")) {
    double lo = 0, hi2 = 0;
    cv::minMaxLoc(disparity, &lo, &hi2);
    std::fprintf(stderr, "%s-%s: f %.1f B %.1f min_d %d num %d -> disparity [%g, %g]\n", a.id.c_str(), b.id.c_str(), f,
                 baseline, min_d, num, lo / 16, hi2 / 16);
  }
  return cv::countNonZero(disparity >= min_d * 16);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Multi-view stereo speed on one frame of a take, beside reading its images and OpenCV's SGBM on the "
      "same pairs"};
  std::string take, calibration = "ground_truth";
  int64_t frame = 0;
  double scale = 1;
  app.add_option("--take", take, "A take with machine-vision frames")->required();
  app.add_option("--calibration", calibration, "Where the cameras are (as stage-process mvs)")->capture_default_str();
  app.add_option("--frame", frame, "The frame")->capture_default_str();
  app.add_option("--image-scale", scale, "Processing resolution relative to the recorded images")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  auto t0 = Clock::now();
  const std::vector<MvsView> views = ReadViews(take, calibration, frame, scale);
  const double read_s = Since(t0);
  if (views.empty()) Die(absl::NotFoundError("no machine-vision views in the take"));
  std::printf("mvs_bench: %zu views of %dx%d (take %s, frame %lld, image scale %.3g)\n", views.size(), views[0].width,
              views[0].height, take.c_str(), static_cast<long long>(frame), scale);
  std::printf("  %-52s %8.2f s\n", "read + undistort the 24 images (baseline)", read_s);

  stage::processing::MvsOptions options;
  const auto neighbours = stage::processing::ChooseNeighbours(views, options);
  t0 = Clock::now();
  int64_t sgbm_pixels = 0;
  for (size_t i = 0; i < views.size(); ++i) {
    // SGBM searches along rows: the nearest neighbour beside the view (on its ring), not above or below it.
    int pair = neighbours[i][0];
    for (int n : neighbours[i]) {
      const Eigen::Vector3d t = views[i].rotation * (views[n].position - views[i].position);
      if (std::abs(t.x()) > std::abs(t.y())) {
        pair = n;
        break;
      }
    }
    sgbm_pixels += Sgbm(views[i], views[pair], options.volume_radius_mm);
  }
  std::printf("  %-52s %8.2f s  (%lld pixels with a disparity)\n",
              "OpenCV SGBM, 24 rectified pairs, 1 thread (baseline)", Since(t0), static_cast<long long>(sgbm_pixels));

  for (int threads : {1, 2}) {
    options.threads = threads;
    t0 = Clock::now();
    auto f = stage::processing::ReconstructFrame(views, options);
    const double all = Since(t0);
    if (!f.ok()) Die(f.status());
    std::printf("  %-52s %8.2f s  (depth %.2f, fusion %.2f, mesh %.2f; %zu vertices)\n",
                threads == 1 ? "multi-view stereo, 1 thread" : "multi-view stereo, 2 threads", all, f->depth_s,
                f->fusion_s, f->mesh_s, f->mesh.positions.size());
  }
  return 0;
}
