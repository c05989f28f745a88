// The stabilization's self-supervised U-Net (docs/assets.md#the-u-net): given a frame's albedo and the reference
// frame's in UV space, it predicts a warp field (where each reference texel is found in the frame) and a wrinkle map
// (the change of the albedo's log-luminance the expression makes, which no warp explains). It learns from the take
// itself: no ground truth, only the losses below, trained on the frames it then stabilizes. libtorch stays behind this
// header (one translation unit includes it).
//
// Inputs are the net's resolution already (the caller averages the textures down and carries the warp back up): two
// channels per texel, the albedo's log-luminance and its coverage (1 covered, 0 not; the value there is ignored).
// A frame may come with a base warp (the optical flow's): the net sees it and predicts a correction to it, F = base +
// net; without one the net predicts the whole warp.
//
// The losses, in our reading of the FaStage paper's equations 2-5 (the warped frame W(F, f), the reference r, the
// wrinkle map k, texels where both are covered):
//   photometric   sum over the pyramid's scales s of mean |avg_s(W(F, f)) - avg_s(r) - avg_s(k)|_eps
//                 (Charbonnier, eps 0.01; each scale warps the frame averaged down by 2^s along the warp averaged
//                 down; k's gradient stops here, so the map cannot explain away a misalignment; a reference texel
//                 the warp takes off the frame's coverage costs 0.3)
//   smoothness    `smoothness` * mean |grad F|^2   (F in texels of the net's resolution)
//   wrinkle fit   mean |W(F, f) - r - k|_eps at full resolution, F's gradient stopped (the map answers to what the
//                 warp leaves)
//   wrinkle       `wrinkle_sparsity` * mean |k| + `wrinkle_smoothness` * mean |grad k|
//   total         their sum
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/processing/photometric.h"

namespace stage::processing {

namespace internal {  // the nets in the torch module (src/torch_nets.h)
class WarpNetNet;
}  // namespace internal

struct WarpNetOptions {
  // U-Net levels (2..6) below the input's 2 x 2 folding: the input's size must divide by 2^levels, twice.
  int levels = 4;
  // Feature channels of the first level, doubled at each level below (4..64).
  int base_channels = 12;
  // Adam steps over the take's frames, one frame each (1..100000). Correcting the optical flow's warp, 300 do as
  // well as 1200 (docs/assets.md#the-u-net); finding the whole warp alone, the net needs 1200 and more (2400 to come
  // near the flow).
  int iterations = 300;
  // Adam's rate (> 0); the last 30 % of the steps at a fifth of it. Twice this trains worse, three times diverges.
  double learning_rate = 1e-3;
  // Scales of the photometric loss's pyramid (1..6): the coarse ones widen the warp's reach.
  int loss_scales = 4;
  double smoothness = 0.2;          // >= 0
  double wrinkle_sparsity = 0.05;   // >= 0
  double wrinkle_smoothness = 0.5;  // >= 0
  // Threads for torch's loops (0: the cores this process may run on); set explicitly, as OpenMP's default spins on a
  // busy machine. The count is the process's (torch's and OpenMP's): concurrent nets share the last one set.
  int threads = 0;
  uint64_t seed = 1;  // the weights' initialization and the frames' order

  absl::Status Validate() const;
};

struct WarpNetPrediction {
  Image flow;     // 2 channels, texels of the net's resolution: reference texel (x, y) is at (x, y) + flow in the frame
  Image wrinkle;  // 1 channel: log-luminance the frame has that the reference has not, at the reference's texels
};

class WarpNet {
 public:
  static absl::StatusOr<std::unique_ptr<WarpNet>> Create(const WarpNetOptions& options);
  ~WarpNet();
  WarpNet(const WarpNet&) = delete;
  WarpNet& operator=(const WarpNet&) = delete;

  // Trains on `frames` against `reference` (all the same size; at least one frame), with `bases` (none, or one warp
  // per frame: 2 channels, texels). `step` gets each step's loss and returns whether to go on (false: Train returns a
  // cancelled error). Errors: inputs of other sizes or channels, a size the levels do not divide, bases that do not
  // match the frames.
  absl::Status Train(const Image& reference, const std::vector<Image>& frames, const std::vector<Image>& bases = {},
                     const std::function<bool(int step, double loss)>& step = {});
  // The warp (base + the net's correction; `base` empty: none) and wrinkle map of `frame`. A net trained with bases
  // needs one here, and one trained without, none.
  absl::StatusOr<WarpNetPrediction> Predict(const Image& reference, const Image& frame, const Image& base = {}) const;
  // The total loss of every step trained so far.
  const std::vector<double>& losses() const;

 private:
  using Impl = internal::WarpNetNet;
  explicit WarpNet(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The threads `threads` stands for: itself, or for 0 the cores this process may run on.
int TorchThreadCount(int threads);

// Sets torch's intra-op threads (0: the cores this process may run on) and, once per process, one inter-op thread;
// returns the count set. Every torch entry point calls it with its options' threads.
int SetTorchThreads(int threads);

// The file of the library whose sgemm_ this process calls (libtorch's BLAS): libopenblas.so.0 when the link order
// holds; empty if none is loaded.
std::string TorchBlasLibrary();

}  // namespace stage::processing
