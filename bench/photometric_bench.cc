// Photometric stereo speed on one full camera set (issue #6: all maps of one 4096x2304 camera in <= 150 ms on 2
// cores), beside baselines measured in the same run on the same input:
//  - the memory-bandwidth floor: reading the cycle's 38 raw frames once;
//  - the maps' floor: writing the solver's output (every map, the flags and its working memory) once;
//  - the fast, table-driven solver (fast_photometric.h), all maps, from the raw mosaic;
//  - the per-pixel solver of the library (photometric.h: demosaiced images, a per-pixel lobe fit), on a band of rows
//    through the face, scaled to the frame's pixels on the subject;
//  - the per-pixel solver again on one pixel in nine (PhotometricSolver::SolveAgain, as after the geometry's refill);
//  - a naive per-pixel implementation (every unit summed per pixel for every normal tried, dense least squares in
//    dynamic matrices, ratios of the first-order specular images), the same way.
// The input: hs-2's cycle of the simulated head (rendered at 1/4 scale, enlarged to the sensor's 4096x2304, then
// exposed at 4000 e- for white, 12-bit Bayer RGGB, with shot and read noise).
// Run: build/bin/photometric_bench [--threads 2] [--repeat 3] [--scale 0.25]
#include <Eigen/Dense>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "CLI/CLI.hpp"
#include "stage/common/rig.h"
#include "stage/processing/calibration.h"
#include "stage/processing/fast_photometric.h"
#include "stage/processing/photometric.h"
#include "stage/sim/light_transport.h"
#include "stage/sim/scene.h"
#include "stage/sim/sensor_model.h"

namespace {

using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

[[noreturn]] void Die(const absl::Status& s) {
  std::fprintf(stderr, "photometric_bench: %s\n", std::string(s.message()).c_str());
  std::exit(1);
}

using stage::processing::CycleFrames;
using stage::processing::Image;
using stage::processing::LightModel;
using stage::processing::PhotometricCamera;

// The naive way: per pixel, per candidate normal, every unit summed; dense weighted least squares in dynamic
// matrices; the specular normal from the ratio of the first-order specular images (Ma et al. 2007).
int64_t NaiveBand(const LightModel& light, const std::vector<Image>& frames, const PhotometricCamera& camera, int y0,
                  int y1) {
  const int np = static_cast<int>(light.patterns.size()) / 2;
  int64_t solved = 0;
  const int w = frames[0].width;
  for (int y = y0; y < y1; ++y) {
    for (int x = 0; x < w; ++x) {
      Eigen::VectorXd d(np), s(np);
      for (int p = 0; p < np; ++p) {
        const float* c = frames[static_cast<size_t>(p)].at(x, y);
        const float* q = frames[static_cast<size_t>(p + np)].at(x, y);
        d[p] = c[0] + c[1] + c[2];
        s[p] = (q[0] + q[1] + q[2]) - d[p];
      }
      if (d[0] < 4) continue;
      Eigen::Vector3d n(0, 0, 1);
      for (int it = 0; it < 3; ++it) {
        Eigen::MatrixXd a(np, 3);
        for (int p = 0; p < np; ++p) a.row(p) = light.DiffuseVector(p, n).transpose() * camera.white_scale;
        Eigen::VectorXd wsqrt = (d.array().max(1.0) / camera.gain_e_per_dn + 75).inverse().sqrt();
        const Eigen::Vector3d u = (wsqrt.asDiagonal() * a).colPivHouseholderQr().solve(wsqrt.asDiagonal() * d);
        if (u.norm() > 0) n = u.normalized();
      }
      // Ratios of the specular gradients (x+ - x-, y+ - y-, z+ - z-) over full-on.
      const Eigen::Vector3d r(s[18] - s[14], s[6] - s[10], s[3] - s[17]);
      volatile double keep = (r.normalized() + Eigen::Vector3d::UnitZ()).normalized().x() + n.x();
      (void)keep;
      ++solved;
    }
  }
  return solved;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Photometric stereo on one 4096x2304 camera set: the fast solver beside the memory floor, the per-pixel "
      "solver and a naive implementation, in the same run",
      "photometric_bench"};
  int threads = 2, repeat = 3;
  bool fast_only = false;
  double scale = 0.25;
  app.add_option("--threads", threads, "Threads for the solvers and the floor")->capture_default_str();
  app.add_option("--repeat", repeat, "Runs of each timed step (the best is kept)")->capture_default_str();
  app.add_option("--scale", scale, "Render scale of the simulated head before enlarging to the sensor")
      ->capture_default_str();
  app.add_flag("--fast-only", fast_only, "Only the floor and the fast solver (skip the slow baselines)");
  CLI11_PARSE(app, argc, argv);

  auto builtin = stage::LoadRig(stage::kBuiltinRigName);
  if (!builtin.ok()) Die(builtin.status());
  auto loaded = stage::ApplyRigOverrides(
      *builtin, {"sim.render_scale=" + std::to_string(scale), "sim.subject.performance=still"});
  if (!loaded.ok()) Die(loaded.status());
  for (auto& c : *loaded->rig.mutable_cameras()) {
    if (c.id() == "hs-2") c.set_pixel_format(stage::v1::PIXEL_FORMAT_BAYER_RG12);
  }
  auto scene = stage::sim::SimScene::FromLoadedRig(*loaded);
  if (!scene.ok()) Die(scene.status());
  const int index = (*scene)->CameraIndex("hs-2");
  const stage::v1::CameraConfig& config = loaded->rig.cameras(index);
  const int w = static_cast<int>(config.width()), h = static_cast<int>(config.height());
  auto light = LightModel::FromRig(*loaded);
  if (!light.ok()) Die(light.status());

  // The input: every pattern's radiance at the render scale, enlarged to the sensor, exposed.
  auto t = Clock::now();
  stage::sim::CameraRenderer renderer(*scene, index);
  const auto responses = renderer.Responses(0);
  const stage::sim::SensorParams& sensor = (*scene)->sensor(index);
  const double exposure_s = config.exposure_us() * 1e-6;
  CycleFrames cycle;
  cycle.width = w;
  cycle.height = h;
  cycle.bits = 12;
  cycle.camera_id = "hs-2";
  for (size_t p = 0; p < light->patterns.size(); ++p) {
    std::vector<float> rgb =
        stage::sim::RenderRadiance(*responses, (*scene)->PatternLevels(static_cast<int>(p)), (*scene)->leakage(index));
    cv::Mat small(responses->height, responses->width, CV_32FC3, rgb.data()), big;
    cv::resize(small, big, {w, h}, 0, 0, cv::INTER_LINEAR);
    std::vector<float> full(big.ptr<float>(0), big.ptr<float>(0) + static_cast<size_t>(w) * h * 3);
    const stage::sim::RawImage raw = stage::sim::ExposeSensor(full, w, h, exposure_s, sensor, 1, 2, p);
    cycle.raw.push_back(raw.data);
  }
  const double setup_s = Since(t);
  t = Clock::now();
  auto setup = stage::processing::ResolveCamera(*loaded, *light, "hs-2", w, h, 12, &(*scene)->true_cameras());
  if (!setup.ok()) Die(setup.status());
  const double rays_s = Since(t);
  stage::processing::PhotometricOptions options;
  options.threads = threads;
  t = Clock::now();
  auto tables = stage::processing::PhotometricTables::Build(*light, setup->camera, options);
  if (!tables.ok()) Die(tables.status());
  const double tables_s = Since(t);

  // The floor: every byte of the 38 raw frames read once (summed), on the same threads.
  const size_t bytes = cycle.raw.size() * cycle.raw[0].size() * sizeof(uint16_t);
  double floor_s = 1e9;
  for (int r = 0; r < repeat; ++r) {
    t = Clock::now();
    std::vector<uint64_t> sums(static_cast<size_t>(threads), 0);
    std::vector<std::thread> pool;
    for (int k = 0; k < threads; ++k) {
      pool.emplace_back([&, k] {
        uint64_t sum = 0;
        for (size_t p = static_cast<size_t>(k); p < cycle.raw.size(); p += static_cast<size_t>(threads)) {
          // Eight bytes at a time: the loop costs nothing beside the memory it reads.
          const auto* words = reinterpret_cast<const uint64_t*>(cycle.raw[p].data());
          const size_t n = cycle.raw[p].size() * sizeof(uint16_t) / sizeof(uint64_t);
          for (size_t i = 0; i < n; ++i) sum += words[i];
        }
        sums[static_cast<size_t>(k)] = sum;
      });
    }
    for (auto& th : pool) th.join();
    floor_s = std::min(floor_s, Since(t));
    if (sums[0] == 42) std::printf(" ");
  }

  // The fast solver, all maps, into the same maps each time (as a take's frames are processed, one after another).
  double fast_s = 1e9;
  int64_t subject = 0;
  stage::processing::PhotometricMaps maps;
  for (int r = 0; r < repeat; ++r) {
    t = Clock::now();
    auto s = stage::processing::SolvePhotometricFast(*light, **tables, cycle, {}, setup->camera, options, &maps);
    fast_s = std::min(fast_s, Since(t));
    if (!s.ok()) Die(s);
    subject = 0;
    for (uint8_t f : maps.flags) subject += (f & stage::processing::kLowSignal) == 0;
  }

  // The maps' floor: every byte of the maps and the solver's working memory (the fast solver's output, all of it
  // written each solve) written once, on the same threads, into the same memory.
  std::vector<std::pair<char*, size_t>> regions;
  for (stage::processing::Image* image :
       {&maps.diffuse_normal_world, &maps.diffuse_normal_camera, &maps.albedo, &maps.specular_normal_world,
        &maps.specular_normal_camera, &maps.specular_normal_raw, &maps.specular, &maps.roughness, &maps.specular_sigma,
        &maps.confidence, &maps.fit_residual}) {
    regions.emplace_back(reinterpret_cast<char*>(image->pixels.data()), image->pixels.size() * sizeof(float));
  }
  regions.emplace_back(reinterpret_cast<char*>(maps.flags.data()), maps.flags.size());
  regions.emplace_back(reinterpret_cast<char*>(maps.work.data()), maps.work.size() * sizeof(float));
  size_t map_bytes = 0;
  for (const auto& [start, size] : regions) map_bytes += size;
  double maps_floor_s = 1e9;
  for (int r = 0; r < repeat; ++r) {
    t = Clock::now();
    std::vector<std::thread> pool;
    for (int k = 0; k < threads; ++k) {
      pool.emplace_back([&, k] {
        for (const auto& [start, size] : regions) {  // each region split between the threads
          const size_t a = size * static_cast<size_t>(k) / static_cast<size_t>(threads);
          const size_t b = size * static_cast<size_t>(k + 1) / static_cast<size_t>(threads);
          std::memset(start + a, 0, b - a);
        }
      });
    }
    for (auto& th : pool) th.join();
    maps_floor_s = std::min(maps_floor_s, Since(t));
  }

  if (fast_only) {
    std::printf(
        "photometric_bench: %.2f M pixels on the subject; floor %.1f ms (%.1f GB/s); maps written once %.1f "
        "ms (%.0f MB); fast solver %.1f ms = %.2fx the floor\n",
        static_cast<double>(subject) / 1e6, 1e3 * floor_s, static_cast<double>(bytes) / floor_s / 1e9,
        1e3 * maps_floor_s, static_cast<double>(map_bytes) / 1e6, 1e3 * fast_s, fast_s / floor_s);
    return 0;
  }
  // The per-pixel solver and the naive one on a band of rows through the middle of the face, scaled to the frame by
  // the pixels on the subject.
  const int band_rows = 64, y0 = h / 2 - band_rows / 2;
  auto images = stage::processing::DemosaicCycle(cycle);
  if (!images.ok()) Die(images.status());
  std::vector<Image> band;
  for (const Image& im : *images) {
    Image b(w, band_rows, 3);
    std::copy(im.pixels.begin() + static_cast<std::ptrdiff_t>(static_cast<size_t>(y0) * w * 3),
              im.pixels.begin() + static_cast<std::ptrdiff_t>(static_cast<size_t>(y0 + band_rows) * w * 3),
              b.pixels.begin());
    band.push_back(std::move(b));
  }
  PhotometricCamera band_camera = setup->camera;
  band_camera.rays.assign(
      setup->camera.rays.begin() + static_cast<std::ptrdiff_t>(static_cast<size_t>(y0) * w),
      setup->camera.rays.begin() + static_cast<std::ptrdiff_t>(static_cast<size_t>(y0 + band_rows) * w));
  auto solver = stage::processing::PhotometricSolver::Create(*light, band, band_camera, options);
  if (!solver.ok()) Die(solver.status());
  t = Clock::now();
  auto exact = (*solver)->Solve(nullptr);
  const double exact_band_s = Since(t);
  if (!exact.ok()) Die(exact.status());
  int64_t band_subject = 0;
  for (uint8_t f : exact->flags) band_subject += (f & stage::processing::kLowSignal) == 0;
  // Solved again on one pixel in nine (11 %: the share of the subject the geometry's refill placed on a half-resolution
  // take), the rest kept; the same geometry (none), so only the time differs.
  stage::processing::PixelGeometry none;
  none.width = w;
  none.height = band_rows;
  none.points.assign(3 * static_cast<size_t>(w) * band_rows, std::nanf(""));
  std::vector<uint8_t> redo(static_cast<size_t>(w) * band_rows, 0);
  for (size_t i = 0; i < redo.size(); i += 9) redo[i] = 1;
  t = Clock::now();
  auto again = (*solver)->SolveAgain(none, redo);
  const double again_band_s = Since(t);
  if (!again.ok()) Die(again.status());
  t = Clock::now();
  std::vector<int64_t> naive_solved(static_cast<size_t>(threads), 0);
  {
    std::vector<std::thread> pool;
    for (int k = 0; k < threads; ++k) {
      pool.emplace_back([&, k] {
        const int a = band_rows * k / threads, b = band_rows * (k + 1) / threads;
        naive_solved[static_cast<size_t>(k)] = NaiveBand(*light, band, band_camera, a, b);
      });
    }
    for (auto& th : pool) th.join();
  }
  const double naive_band_s = Since(t);
  const double per_frame = static_cast<double>(subject) / std::max<int64_t>(1, band_subject);

  std::printf(
      "photometric_bench: hs-2 at %dx%d (38 patterns, 12-bit BayerRG, the simulated head rendered at %.2f "
      "and enlarged), %.2f M pixels on the subject, %d threads, best of %d\n",
      w, h, scale, static_cast<double>(subject) / 1e6, threads, repeat);
  std::printf("  input made in %.1f s; camera rays %.2f s and tables %.2f s (once per camera)\n", setup_s, rays_s,
              tables_s);
  std::printf("  memory floor: read the 38 raw frames once   %8.1f ms  (%.0f MB, %.1f GB/s)\n", 1e3 * floor_s,
              static_cast<double>(bytes) / 1e6, static_cast<double>(bytes) / floor_s / 1e9);
  std::printf("  maps floor: write the maps once             %8.1f ms  (%.0f MB, %.1f GB/s)\n", 1e3 * maps_floor_s,
              static_cast<double>(map_bytes) / 1e6, static_cast<double>(map_bytes) / maps_floor_s / 1e9);
  std::printf("  fast solver, all maps                       %8.1f ms  = %.2fx the floor (goal <= 150 ms)\n",
              1e3 * fast_s, fast_s / floor_s);
  std::printf(
      "  per-pixel solver (lobe fit per pixel)       %8.1f s   = %.0fx the fast solver (%d rows, %lld pixels "
      "on the subject, scaled)\n",
      exact_band_s * per_frame, exact_band_s * per_frame / fast_s, band_rows, static_cast<long long>(band_subject));
  std::printf(
      "  naive per-pixel (unit sums, dense LS)       %8.1f s   = %.0fx the fast solver (the same rows, scaled)\n",
      naive_band_s * per_frame, naive_band_s * per_frame / fast_s);
  std::printf(
      "  per-pixel solver again on 1 pixel in 9      %8.1f s   = %.2fx its whole solve (the same rows, scaled; the "
      "others' fits kept)\n",
      again_band_s * per_frame, again_band_s / exact_band_s);
  return 0;
}
