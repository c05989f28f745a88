// The simulator's rendering cost, with baselines measured in the same run:
//  1. per camera and scale (default hs-2 at full 4096x2304 and at 1/4): the per-pose precompute (every pixel's
//     response to every LED unit, with shadow rays) and the per-pattern render (two matrix-vector products, then the
//     sensor model), next to a bare loop computing the same dot products pixel by pixel;
//  2. the precompute's shadow rays on that camera's view of the head (every pixel towards every unit it faces), on one
//     thread, traced as the renderer traces them (the rays of 16 neighbouring pixels towards one unit after another,
//     as one stream: Subject::OccludedMany) beside the same rays one at a time (Subject::Occluded) and as streams of
//     one pixel's rays (towards every unit: one origin, directions apart);
//  3. the whole rig at the demo scale through the lockstep world for a take (default 912 slots = 1 s): wall time per
//     second of take, frames rendered per second; each camera's responses summed under the patterns of its slots (as
//     the stage renders) beside every unit's responses;
//  4. a full-lit take's camera frames (default mv-05 watching the ChArUco board move through 6 poses at render scale
//     0.5, each pose's full-on patterns, as `stage-sim-render --take` renders a calibration take): each pose's sums
//     under its exposures alone (ExposureBasis, every sub-pixel offset's rays kept) beside every unit's responses (the
//     renderer's way for a live stage, rays kept within their default budget), the frames compared.
// Run: build/bin/sim_render_bench [--scales 1,0.25] [--shadow-scale 0.25] [--shadow-rounds 3] [--demo-scale 0.04]
//      [--slots 912] [--camera hs-2] [--full-lit-scale 0.5] [--full-lit-poses 6] [--full-lit-camera mv-05]
#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <mutex>
#include <span>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "stage/common/clock.h"
#include "stage/common/rig.h"
#include "stage/sim/world_devices.h"
#include "stage/timing/schedule.h"

namespace {

using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

[[noreturn]] void Die(const absl::Status& s) {
  std::fprintf(stderr, "sim_render_bench: %s\n", std::string(s.message()).c_str());
  std::exit(1);
}

std::shared_ptr<const stage::sim::SimScene> Scene(double scale, const std::string& performance) {
  auto loaded = stage::LoadRig(stage::kBuiltinRigName);
  if (!loaded.ok()) Die(loaded.status());
  auto rig = stage::ApplyRigOverrides(
      *loaded, {"sim.render_scale=" + std::to_string(scale), "sim.subject.performance=" + performance});
  if (!rig.ok()) Die(rig.status());
  auto scene = stage::sim::SimScene::FromLoadedRig(*rig);
  if (!scene.ok()) Die(scene.status());
  return *scene;
}

void OneCamera(const std::string& camera, double scale) {
  auto scene = Scene(scale, "still");
  const int index = scene->CameraIndex(camera);
  if (index < 0) Die(absl::NotFoundError("no camera " + camera));
  stage::sim::CameraRenderer renderer(scene, index);
  auto t = Clock::now();
  auto r = renderer.Responses(0);
  const double precompute = Since(t);
  const int patterns = static_cast<int>(stage::timing::CycleLength(scene->schedule()));
  std::vector<stage::sim::EmitterLevels> levels;
  for (int p = 0; p < patterns; ++p) levels.push_back(scene->PatternLevels(p));
  const float leak = scene->leakage(index);
  // Radiance only (the matrix products), then with the sensor model.
  t = Clock::now();
  double checksum = 0;
  for (int p = 0; p < patterns; ++p) checksum += stage::sim::RenderRadiance(*r, levels[p], leak)[0];
  const double radiance = Since(t) / patterns;
  t = Clock::now();
  for (int p = 0; p < patterns; ++p) checksum += renderer.Render(levels[p], 900e-6, static_cast<uint64_t>(p)).data[0];
  const double full = Since(t) / patterns;
  // Baseline: the same two dot products per pixel in a bare loop.
  t = Clock::now();
  const auto rows = r->diffuse.rows(), cols = r->diffuse.cols();
  for (int p = 0; p < patterns; ++p) {
    const Eigen::VectorXf dd = levels[p].cross + levels[p].parallel;
    const Eigen::VectorXf sd = levels[p].parallel + leak * levels[p].cross;
    double sum = 0;
    for (Eigen::Index i = 0; i < rows; ++i) {
      const float* drow = r->diffuse.data() + i * cols;
      const float* srow = r->specular.data() + i * cols;
      float d = 0, s = 0;
      for (Eigen::Index l = 0; l < cols; ++l) {
        d += drow[l] * dd[l];
        s += srow[l] * sd[l];
      }
      sum += d + s;
    }
    checksum += sum;
  }
  const double bare = Since(t) / patterns;
  std::printf(
      "%-5s scale %-5g %5dx%-5d %8zu subject pixels x %zu units: precompute %8.2f s (%.1f GB); per pattern: "
      "radiance %8.2f ms, with sensor %8.2f ms; bare dot-product loop %8.2f ms   [checksum %.3g]\n",
      camera.c_str(), scale, r->width, r->height, r->pixels.size(), scene->dome().units.size(), precompute,
      2.0 * rows * cols * 4 / 1e9, radiance * 1e3, full * 1e3, bare * 1e3, checksum);
}

// Shadow rays like the renderer's: from each hit (lifted 1e-3 mm off along its geometric normal) towards each unit in
// front of it (its facing test, written here in its own terms), grouped in blocks of `block` neighbouring hits,
// unit-major within a block (`unit_major`) or hit-major (each hit's rays together).
struct ShadowRays {
  std::vector<Eigen::Vector3f> from, to;
  std::vector<size_t> block_starts;
};

ShadowRays MakeShadowRays(const std::vector<stage::sim::Hit>& hits, const stage::sim::Dome& dome, size_t block,
                          bool unit_major) {
  std::vector<const stage::sim::Hit*> seen;
  for (const auto& h : hits) {
    if (h.hit) seen.push_back(&h);
  }
  ShadowRays rays;
  auto add = [&](const stage::sim::Hit& h, const stage::sim::LedUnitModel& u) {
    const Eigen::Vector3f to = u.position.cast<float>();
    if ((to - h.point).dot(h.geometric_normal) <= 0 || (to - h.point).dot(h.normal) <= 0) return;
    rays.from.push_back(h.point + 1e-3f * h.geometric_normal);
    rays.to.push_back(to);
  };
  for (size_t first = 0; first < seen.size(); first += block) {
    rays.block_starts.push_back(rays.from.size());
    const size_t last = std::min(seen.size(), first + block);
    if (unit_major) {
      for (const auto& u : dome.units) {
        for (size_t k = first; k < last; ++k) add(*seen[k], u);
      }
    } else {
      for (size_t k = first; k < last; ++k) {
        for (const auto& u : dome.units) add(*seen[k], u);
      }
    }
  }
  rays.block_starts.push_back(rays.from.size());
  return rays;
}

void ShadowRayCost(const std::string& camera, double scale, int rounds) {
  auto scene = Scene(scale, "still");
  const int index = scene->CameraIndex(camera);
  if (index < 0) Die(absl::NotFoundError("no camera " + camera));
  const auto subject = scene->SubjectAt(0);
  const std::vector<stage::sim::Hit> hits = stage::sim::TracePixels(scene->camera(index), *subject, 1);
  // Each way's answers in its rays' order.
  auto streams = [&](const ShadowRays& rays, std::vector<uint8_t>* answers) {
    answers->assign(rays.from.size(), 0);
    const auto t = Clock::now();
    for (size_t b = 0; b + 1 < rays.block_starts.size(); ++b) {
      const size_t first = rays.block_starts[b], n = rays.block_starts[b + 1] - first;
      subject->OccludedMany(std::span(rays.from).subspan(first, n), std::span(rays.to).subspan(first, n),
                            std::span(*answers).subspan(first, n));
    }
    return Since(t);
  };
  const ShadowRays coherent = MakeShadowRays(hits, scene->dome(), 16, true);
  const ShadowRays per_pixel = MakeShadowRays(hits, scene->dome(), 1, false);
  // The three ways in turn, `rounds` times; each way's median. The one at a time and the renderer's way trace the
  // same rays in the same order, compared answer by answer; one pixel's streams hold them in another order, compared
  // by their count.
  std::vector<double> one_s, coherent_s, pixel_s;
  std::vector<uint8_t> one(coherent.from.size()), together, pixel;
  for (int round = 0; round < rounds; ++round) {
    const auto t = Clock::now();
    for (size_t i = 0; i < coherent.from.size(); ++i) one[i] = subject->Occluded(coherent.from[i], coherent.to[i]);
    one_s.push_back(Since(t));
    coherent_s.push_back(streams(coherent, &together));
    pixel_s.push_back(streams(per_pixel, &pixel));
  }
  const auto median = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  const size_t blocked = std::count(one.begin(), one.end(), 1);
  const bool agree = one == together && static_cast<size_t>(std::count(pixel.begin(), pixel.end(), 1)) == blocked;
  const double rays = static_cast<double>(coherent.from.size());
  const double a = median(one_s), b = median(coherent_s), c = median(pixel_s);
  std::printf(
      "%-5s scale %-5g shadow rays, one thread, median of %d rounds: %zu rays (%.1f %% blocked%s): one at a time "
      "%.2f s (%.2f M rays/s); 16 pixels towards one unit after another, one stream a block (the renderer) %.2f s "
      "(%.2f M rays/s, %.2fx); one pixel's rays a stream %.2f s (%.2f M rays/s, %.2fx)\n",
      camera.c_str(), scale, rounds, coherent.from.size(), 100.0 * static_cast<double>(blocked) / rays,
      agree ? ", the same answers" : ", THE WAYS DISAGREE", a, rays / a / 1e6, b, rays / b / 1e6, a / b, c,
      rays / c / 1e6, a / c);
  if (!agree) std::exit(1);
}

class CountingSink : public stage::camera::FrameSink {
 public:
  void OnFrame(std::shared_ptr<const stage::camera::Frame>) override {
    std::lock_guard<std::mutex> lock(mutex_);
    ++frames_;
    cv_.notify_all();
  }
  void WaitFor(uint64_t n) {
    std::unique_lock<std::mutex> lock(mutex_);
    cv_.wait(lock, [&] { return frames_ >= n; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  uint64_t frames_ = 0;
};

// `sums`: each camera's responses summed under the patterns of its slots, as the stage renders them (CameraWorld);
// false: every unit's responses (the baseline).
void WholeRig(double scale, int64_t slots, bool sums) {
  auto t = Clock::now();
  auto scene = Scene(scale, "default");
  const double setup = Since(t);
  stage::sim::WorldOptions options = scene->MakeWorldOptions(true, 0);
  options.end_slot = slots;
  stage::sim::World world(scene->dome(), options);
  auto client = stage::sim::LocalWorldClient(&world);
  std::vector<std::unique_ptr<stage::sim::SimLightDriver>> lights;
  for (const auto& n : scene->rig().light_nodes()) {
    lights.push_back(std::make_unique<stage::sim::SimLightDriver>(n.id(), n.channel_count()));
    if (auto s = stage::sim::JoinLightNode(lights.back().get(), *scene, n.id(), client.get()); !s.ok()) Die(s);
  }
  stage::SimClock clock;
  std::vector<std::unique_ptr<CountingSink>> sinks;
  std::vector<std::unique_ptr<stage::sim::SimCameraDevice>> cameras;
  std::vector<uint64_t> expected;
  uint64_t total = 0;
  for (int i = 0; i < scene->rig().cameras_size(); ++i) {
    const auto& c = scene->rig().cameras(i);
    auto device = std::make_unique<stage::sim::SimCameraDevice>(&clock, c.id());
    if (auto s = device->Configure({c.width(), c.height(), stage::PixelFormatName(c.pixel_format()), c.frame_rate_hz(),
                                    c.exposure_us(), c.gain_db(), stage::camera::TriggerMode::kHardware});
        !s.ok()) {
      Die(s);
    }
    auto plan = stage::sim::CameraWorld(scene, c.id(), client.get());
    if (!plan.ok()) Die(plan.status());
    if (!sums) plan->renderer->ExpectOnly({});
    if (auto s = device->AttachWorld(*plan); !s.ok()) Die(s);
    sinks.push_back(std::make_unique<CountingSink>());
    if (auto s = device->Start(sinks.back().get()); !s.ok()) Die(s);
    const auto& timing = scene->schedule().cameras(i);
    uint64_t n = 0;
    for (int64_t k = 0; k < slots; ++k) n += stage::timing::FiresInSlot(timing, k);
    expected.push_back(n);
    total += n;
    cameras.push_back(std::move(device));
  }
  t = Clock::now();
  world.Start();
  for (size_t i = 0; i < sinks.size(); ++i) sinks[i]->WaitFor(expected[i]);
  const double wall = Since(t);
  for (auto& c : cameras) (void)c->Stop();
  const double take_s = static_cast<double>(slots) / scene->base().slot_rate_hz();
  std::printf(
      "whole rig at scale %g, %s (hs %dx%d, mv %dx%d), %lld slots = %.3f s of take, %zu cameras, %d poses: "
      "%llu frames in %.1f s wall (%.1f s per second of take, %.0f frames/s); scene set-up %.2f s\n",
      scale, sums ? "responses summed under each camera's patterns (the stage)" : "every unit's responses (baseline)",
      scene->camera(scene->CameraIndex("hs-2")).width(), scene->camera(scene->CameraIndex("hs-2")).height(),
      scene->camera(0).width(), scene->camera(0).height(), static_cast<long long>(slots), take_s, cameras.size(),
      static_cast<int>((slots + 37) / 38), static_cast<unsigned long long>(total), wall, wall / take_s, total / wall,
      setup);
}

void FullLitTake(const std::string& camera, double scale, int poses) {
  auto loaded = stage::LoadRig(stage::kBuiltinRigName);
  if (!loaded.ok()) Die(loaded.status());
  auto rig =
      stage::ApplyRigOverrides(*loaded, {"sim.render_scale=" + std::to_string(scale), "sim.subject.kind=charuco"});
  if (!rig.ok()) Die(rig.status());
  auto made = stage::sim::SimScene::FromLoadedRig(*rig);
  if (!made.ok()) Die(made.status());
  const std::shared_ptr<const stage::sim::SimScene> scene = *made;
  const int index = scene->CameraIndex(camera);
  if (index < 0) Die(absl::NotFoundError("no camera " + camera));
  std::vector<stage::sim::EmitterLevels> full_on;
  for (const int p : scene->FullOnPatterns()) full_on.push_back(scene->PatternLevels(p));
  if (full_on.empty()) Die(absl::FailedPreconditionError("the schedule has no full-on pattern"));
  const double exposure_s = scene->rig().cameras(index).exposure_us() * 1e-6;
  // Each way renders the same camera frames (pose x full-on pattern, the same noise); its time and its frames.
  auto render = [&](bool basis, std::vector<stage::sim::RawImage>* frames) {
    stage::sim::CameraRenderer renderer(scene, index);
    if (basis) {
      renderer.ExpectOnly(full_on);
      renderer.KeepRays(size_t{4} << 30);
    }
    const auto t = Clock::now();
    uint64_t counter = 0;
    for (int pose = 0; pose < poses; ++pose) {
      for (const auto& levels : full_on) frames->push_back(renderer.Render(levels, exposure_s, counter++, pose * 2));
    }
    return Since(t);
  };
  std::vector<stage::sim::RawImage> every, few;
  const double every_s = render(false, &every);
  const double few_s = render(true, &few);
  size_t differ = 0, values = 0;
  int worst = 0;
  for (size_t f = 0; f < every.size(); ++f) {
    for (size_t i = 0; i < every[f].data.size(); ++i) {
      const int d = std::abs(static_cast<int>(every[f].data[i]) - static_cast<int>(few[f].data[i]));
      differ += d != 0;
      worst = std::max(worst, d);
    }
    values += every[f].data.size();
  }
  const double frames = static_cast<double>(every.size());
  std::printf(
      "%-5s scale %-5g full-lit take of the board, %d poses x %zu full-on pattern(s), %dx%d: every unit's responses "
      "%.2f s (%.2f s a camera frame); the take's exposures alone %.2f s (%.2f s a camera frame, %.2fx); %zu of %zu "
      "values differ, by at most %d DN\n",
      camera.c_str(), scale, poses, full_on.size(), every.front().width, every.front().height, every_s,
      every_s / frames, few_s, few_s / frames, every_s / few_s, differ, values, worst);
  if (worst > 1) std::exit(1);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Simulator rendering cost: per-camera precompute and per-pattern render at several scales (next to a "
      "bare dot-product loop), and the whole rig through the lockstep world at the demo scale.",
      "sim_render_bench"};
  std::vector<double> scales = {1.0, 0.25};
  double demo_scale = 0.04;
  int64_t slots = 912;
  std::string camera = "hs-2";
  double shadow_scale = 0.25;
  int shadow_rounds = 3;
  app.add_option("--scales", scales, "Render scales for the one-camera figures")->delimiter(',')->capture_default_str();
  app.add_option("--shadow-scale", shadow_scale, "Render scale of the shadow rays' figures (0 skips them)")
      ->capture_default_str();
  app.add_option("--shadow-rounds", shadow_rounds, "Rounds of the shadow rays' figures (their medians)")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--demo-scale", demo_scale, "Render scale of the whole-rig run (0 skips it)")->capture_default_str();
  app.add_option("--slots", slots, "Slots of the whole-rig run")->capture_default_str();
  app.add_option("--camera", camera, "Camera of the one-camera figures")->capture_default_str();
  double full_lit_scale = 0.5;
  int full_lit_poses = 6;
  std::string full_lit_camera = "mv-05";
  app.add_option("--full-lit-scale", full_lit_scale, "Render scale of the full-lit take's figures (0 skips them)")
      ->capture_default_str();
  app.add_option("--full-lit-poses", full_lit_poses, "Poses of the board in the full-lit take")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--full-lit-camera", full_lit_camera, "Camera of the full-lit take")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  std::printf("sim_render_bench on %u hardware threads\n", std::thread::hardware_concurrency());
  for (double s : scales) OneCamera(camera, s);
  if (shadow_scale > 0) ShadowRayCost(camera, shadow_scale, shadow_rounds);
  if (demo_scale > 0) {
    WholeRig(demo_scale, slots, /*sums=*/false);
    WholeRig(demo_scale, slots, /*sums=*/true);
  }
  if (full_lit_scale > 0) FullLitTake(full_lit_camera, full_lit_scale, full_lit_poses);
  return 0;
}
