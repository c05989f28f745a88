// The stabilization's U-Net (docs/assets.md#the-u-net): one training step and one prediction at the net's size,
// beside baselines measured in the same run: OpenBLAS multiplying matrices of the same arithmetic as a training step
// (what the CPU does when nothing but multiply-adds is asked of it), and the optical flow (OpenCV's DIS) the U-Net
// starts from, on the same frames. The frames are a skin-like pattern (blotches and pores) moved by a texel or two.
// Run: build/bin/stabilize_bench [--size 256] [--steps 60] [--threads 0]
#include <cblas.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <vector>

#include "CLI/CLI.hpp"
#include "stage/processing/stabilize.h"
#include "stage/processing/warp_net.h"

namespace {

using Steady = std::chrono::steady_clock;
double Since(Steady::time_point t) { return std::chrono::duration<double>(Steady::now() - t).count(); }

// The pattern's log-luminance at (u, v).
float LogLuminance(float u, float v) {
  return std::log(0.5f + 0.1f * std::sin(0.21f * u) * std::cos(0.17f * v) + 0.05f * std::sin(0.35f * u + 0.5f * v) +
                  0.03f * std::sin(1.3f * u + 0.7f * v) * std::cos(0.9f * u - 1.1f * v));
}

// The net's input (log-luminance, coverage) and the same as fused textures, moved by (dx, dy).
stage::processing::Image NetFrame(int size, float dx, float dy) {
  stage::processing::Image out(size, size, 2);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      out.at(x, y)[0] = LogLuminance(static_cast<float>(x) - dx, static_cast<float>(y) - dy);
      out.at(x, y)[1] = 1;
    }
  }
  return out;
}

stage::processing::FusedTextures Textures(int size, float dx, float dy) {
  stage::processing::FusedTextures t;
  t.size = size;
  t.albedo = stage::processing::Image(size, size, 3);
  t.state.assign(static_cast<size_t>(size) * size, stage::processing::TexelState::kCovered);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const float l = std::exp(LogLuminance(static_cast<float>(x) - dx, static_cast<float>(y) - dy));
      for (int c = 0; c < 3; ++c) t.albedo.at(x, y)[c] = l;
    }
  }
  return t;
}

// Multiply-adds of one forward pass of the default U-Net (warp_net.cc) on a size x size input: the 2 x 2 folding
// (6 x 4 channels at half size), two 3 x 3 convolutions per level down and up, the head.
double ForwardMacs(int size, int levels, int base) {
  double macs = 0;
  int in = 24;
  for (int l = 0; l < levels; ++l) {
    const double r = static_cast<double>(size / 2 >> l), c = base << l;
    macs += r * r * 9 * (in * c + c * c);
    if (l + 1 < levels) macs += r * r * 9 * ((2 * c + c) * c + c * c);  // up: the level below's channels + the skip
    in = static_cast<int>(c);
  }
  const double r0 = size / 2.0;
  return macs + r0 * r0 * 9 * base * 12;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app("The stabilization's U-Net: a training step and a prediction, beside OpenBLAS and the optical flow");
  int size = 256, steps = 60, threads = 0;
  app.add_option("--size", size, "The net's size, texels across (a power of two)")->capture_default_str();
  app.add_option("--steps", steps, "Training steps to time")->capture_default_str()->check(CLI::Range(2, 100000));
  app.add_option("--threads", threads, "Torch's threads (0: the machine's cores)")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  using namespace stage::processing;

  WarpNetOptions options;
  options.iterations = steps;
  options.threads = threads;
  const int used = SetTorchThreads(threads);
  auto net = WarpNet::Create(options);
  if (!net.ok()) {
    std::fprintf(stderr, "stabilize_bench: %s\n", std::string(net.status().message()).c_str());
    return 1;
  }
  const Image reference = NetFrame(size, 0, 0);
  const std::vector<Image> frames = {NetFrame(size, 1.5f, -1.0f), NetFrame(size, -1.0f, 1.5f)};
  const std::vector<Image> bases(frames.size(), Image(size, size, 2));
  // The first step (allocations, oneDNN's kernel choice) apart.
  Steady::time_point first;
  double first_s = 0;
  auto t = Steady::now();
  const absl::Status trained = (*net)->Train(reference, frames, bases, [&](int step, double) {
    if (step == 0) {
      first_s = Since(t);
      first = Steady::now();
    }
    return true;
  });
  const double step_s = Since(first) / (steps - 1);
  if (!trained.ok()) {
    std::fprintf(stderr, "stabilize_bench: %s\n", std::string(trained.message()).c_str());
    return 1;
  }
  t = Steady::now();
  for (int i = 0; i < 5; ++i) (void)(*net)->Predict(reference, frames[0], bases[0]);
  const double predict_s = Since(t) / 5;

  // Baseline: OpenBLAS's sgemm of a training step's multiply-adds (forward, and twice that backward).
  const double step_macs = 3 * ForwardMacs(size, options.levels, options.base_channels);
  const int n = static_cast<int>(std::cbrt(step_macs));
  std::vector<float> a(static_cast<size_t>(n) * n, 0.5f), b(a.size(), 0.25f), c(a.size(), 0.0f);
  openblas_set_num_threads(used);
  cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, n, n, n, 1, a.data(), n, b.data(), n, 0, c.data(), n);
  t = Steady::now();
  for (int i = 0; i < 3; ++i) {
    cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, n, n, n, 1, a.data(), n, b.data(), n, 0, c.data(), n);
  }
  const double gemm_s = Since(t) / 3;
  openblas_set_num_threads(1);

  // Baseline: the optical flow the U-Net starts from, on the same frames.
  const FusedTextures ref_t = Textures(size, 0, 0), moved = Textures(size, 1.5f, -1.0f);
  (void)StabilizeTextures(ref_t, moved, {});
  t = Steady::now();
  for (int i = 0; i < 3; ++i) (void)StabilizeTextures(ref_t, moved, {});
  const double flow_s = Since(t) / 3;

  const double gflop = 2 * step_macs / 1e9;
  std::printf("U-Net at %d x %d, %d thread(s): %.2f GFLOP of convolutions per training step\n", size, size, used,
              gflop);
  std::printf("training step                 %8.1f ms  (%5.1f GFLOP/s; the first step %.1f ms)\n", 1e3 * step_s,
              gflop / step_s, 1e3 * first_s);
  std::printf("  %d steps (the default)     %8.1f s\n", WarpNetOptions{}.iterations,
              WarpNetOptions{}.iterations * step_s);
  std::printf("prediction (one frame)        %8.1f ms\n", 1e3 * predict_s);
  std::printf("baseline: OpenBLAS sgemm %d^3 %7.1f ms  (%5.1f GFLOP/s)\n", n, 1e3 * gemm_s,
              2.0 * n * n * n / 1e9 / gemm_s);
  std::printf("baseline: optical flow (DIS)  %8.1f ms  per frame, warping the textures included\n", 1e3 * flow_s);
  return 0;
}
