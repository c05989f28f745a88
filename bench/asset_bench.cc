// The neural asset's training throughput (docs/asset.md#speed): the geometry VAE's training steps at its options,
// beside the floor measured in the same run: one plain 3 x 3 convolution's forward and backward in the same torch,
// at the size and channels where the VAE spends most of its arithmetic (what the CPU gives torch's convolutions when
// nothing else is asked of it). Maps are made up (a dome and a moving bulge); the step's cost does not depend on
// them.
// Run: build/bin/asset_bench [--steps 30] [--batch 16] [--threads 0] [--input-size 64] [--levels 4] [--json]
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "CLI/CLI.hpp"
#include "stage/processing/asset_net.h"
#include "stage/processing/warp_net.h"

namespace {

using Steady = std::chrono::steady_clock;
double Since(Steady::time_point t) { return std::chrono::duration<double>(Steady::now() - t).count(); }

std::vector<float> Map(int size, float bulge) {
  std::vector<float> m(3 * static_cast<size_t>(size) * size);
  const size_t n = static_cast<size_t>(size) * size;
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const float u = 200.f * x / size - 100, v = 150.f * y / size - 60;
      const size_t t = static_cast<size_t>(y) * size + x;
      m[t] = u;
      m[n + t] = v;
      m[2 * n + t] = 90 - 0.004f * (u * u + v * v) + bulge * std::exp(-(u * u + v * v) / 800);
    }
  }
  return m;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Times the neural asset's geometry VAE training step beside a plain convolution's (docs/asset.md)"};
  int steps = 30, threads = 0;
  stage::processing::GeometryVaeOptions options;
  int batch = 16;
  bool json = false;
  app.add_option("--steps", steps, "Training steps timed")->capture_default_str();
  app.add_option("--batch", batch, "Maps a step")->capture_default_str();
  app.add_option("--threads", threads, "Torch's threads (0: the cores this process may use)")->capture_default_str();
  app.add_option("--input-size", options.input_size, "Texels across a map")->capture_default_str();
  app.add_option("--levels", options.levels, "The net's stride-2 levels")->capture_default_str();
  app.add_flag("--json", json, "Print the figures as JSON");
  CLI11_PARSE(app, argc, argv);
  options.threads = threads;
  const int size = options.input_size;
  const size_t texels = static_cast<size_t>(size) * size;
  auto net = stage::processing::GeometryVae::Create(options, Map(size, 0), 2.0f);
  if (!net.ok()) {
    std::fprintf(stderr, "%s\n", std::string(net.status().message()).c_str());
    return 1;
  }
  std::mt19937 rng(1);
  std::normal_distribution<float> normal;
  stage::processing::GeometryBatch b;
  b.batch = batch;
  for (int i = 0; i < batch; ++i) {
    const std::vector<float> m = Map(size, static_cast<float>(i % 7));
    b.posed.insert(b.posed.end(), m.begin(), m.end());
    b.canonical.insert(b.canonical.end(), m.begin(), m.end());
    b.valid.insert(b.valid.end(), texels, 1.f);
    for (int l = 0; l < options.geometry_latent + options.pose_latent; ++l) b.noise.push_back(normal(rng));
  }
  if (auto warm = (*net)->TrainStep(b, 1e-3); !warm.ok()) {
    std::fprintf(stderr, "%s\n", std::string(warm.status().message()).c_str());
    return 1;
  }
  const auto start = Steady::now();
  for (int i = 0; i < steps; ++i) (void)(*net)->TrainStep(b, 1e-3);
  const double step_s = Since(start) / steps;
  const double macs = 3 * stage::processing::GeometryVaeForwardMacs(options) * batch;
  // The floor: the VAE's widest full-resolution convolution's shape class (its second level: size / 2, 2 x base
  // channels), same batch.
  const int floor_size = size / 2, floor_channels = 2 * options.base_channels;
  auto floor = stage::processing::ConvFloorMacsPerSecond(floor_size, floor_channels, batch, steps, threads);
  if (!floor.ok()) {
    std::fprintf(stderr, "%s\n", std::string(floor.status().message()).c_str());
    return 1;
  }
  const int used = stage::processing::TorchThreadCount(threads);
  if (json) {
    std::printf(
        "{\"threads\": %d, \"batch\": %d, \"step_s\": %.5f, \"samples_per_s\": %.2f, \"vae_gmacs_per_s\": %.3f, "
        "\"floor_gmacs_per_s\": %.3f, \"weights\": %lld}\n",
        used, batch, step_s, batch / step_s, macs / step_s * 1e-9, *floor * 1e-9,
        static_cast<long long>((*net)->parameter_count()));
  } else {
    std::printf("geometry VAE (%lld weights, input %d, %d threads), training step of %d maps:\n",
                static_cast<long long>((*net)->parameter_count()), size, used, batch);
    std::printf("  %.1f ms a step, %.1f maps/s, %.2f GMAC/s (forward and backward, %.2f GMAC a step)\n", 1e3 * step_s,
                batch / step_s, macs / step_s * 1e-9, macs * 1e-9);
    std::printf("floor: one 3x3 convolution %d -> %d channels at %d x %d, forward and backward: %.2f GMAC/s\n",
                floor_channels, floor_channels, floor_size, floor_size, *floor * 1e-9);
    std::printf("the VAE's step runs at %.0f %% of the floor's rate\n", 100 * macs / step_s / *floor);
  }
  return 0;
}
