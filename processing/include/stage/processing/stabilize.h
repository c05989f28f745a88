// Temporal stabilization of fused UV textures (docs/assets.md#temporal-stabilization). A fit that slides along the
// skin moves the skin's texture about the UV layout from frame to frame: pores and freckles drift and the textures
// shimmer when played. Each frame's textures are warped onto a reference frame's (the neutral one) along a warp field
// found on the two albedos in UV space; the other maps follow the same warp. Two ways to find it: the optical-flow
// baseline (OpenCV's DIS on the albedo's luminance, frame by frame), and the self-supervised U-Net (warp_net.h),
// trained on the take's frames, which also gives a wrinkle map. The warp is smooth, so a wrinkle (a change of the
// normals, not of the albedo) is carried along, not flattened.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/processing/texture_fusion.h"
#include "stage/processing/warp_net.h"

namespace stage::processing {

enum class StabilizeMethod {
  kFlow,  // OpenCV's DIS optical flow, each frame against the reference
  kUNet,  // the self-supervised U-Net trained on the frames (warp_net.h)
};
absl::string_view StabilizeMethodName(StabilizeMethod method);  // "flow", "unet"
absl::StatusOr<StabilizeMethod> ParseStabilizeMethod(absl::string_view name);

struct StabilizeOptions {
  StabilizeMethod method = StabilizeMethod::kFlow;
  // The flow's options (kFlow).
  // DIS's patch size and the stride between patches, texels (4..64, 1..patch_size).
  int patch_size = 12;
  int patch_stride = 4;
  // Variational refinement iterations per scale (0: none).
  int refinement_iterations = 5;
  // A flow longer than this, texels, is not trusted: the texel keeps its own value (> 0).
  double max_flow_px = 40;
  // The U-Net's (kUNet): the resolution it works at, texels across (a power of two from 32 up; the textures are
  // averaged down to it when larger, and its warp and wrinkle map carried back up), and the net and its training.
  int net_size = 256;
  WarpNetOptions net;
  // The U-Net corrects the optical flow's warp (sees it and adds to it) rather than finding the whole warp.
  bool net_from_flow = true;

  absl::Status Validate() const;
};

struct StabilizedTextures {
  FusedTextures textures;   // the frame's, on the reference's texels
  Image flow;               // 2 channels: where each reference texel is found in the frame, texels
  double mean_flow_px = 0;  // over the texels both cover
  // kUNet: 1 channel, the albedo's log-luminance the frame has that the reference has not (the net's wrinkle map, at
  // the textures' size); empty for kFlow.
  Image wrinkle;
};

// Every frame of `frames` warped onto `reference` (a frame may be the reference itself), by either method; the U-Net is
// trained on `frames` first. Errors: options out of range, textures of different sizes.
absl::StatusOr<std::vector<StabilizedTextures>> StabilizeSequence(const FusedTextures& reference,
                                                                  const std::vector<FusedTextures>& frames,
                                                                  const StabilizeOptions& options);

// `frame`'s textures warped onto `reference`'s texels along the optical flow (whatever `options.method`). Errors:
// options out of range, textures of different sizes.
absl::StatusOr<StabilizedTextures> StabilizeTextures(const FusedTextures& reference, const FusedTextures& frame,
                                                     const StabilizeOptions& options);

// The albedo's jitter between two frames' textures (the FaStage paper's Fig. 17 measure): over the texels `a` and `b`
// both cover (and `mask` holds, if given), the mean of |la - lb| / ((la + lb) / 2), l the albedo's luminance.
double AlbedoJitter(const FusedTextures& a, const FusedTextures& b, const std::vector<bool>* mask = nullptr);

// The stage (docs/assets.md#temporal-stabilization): the fused textures of a take's frames
// (TAKE/derived/textures/frame-NNNNNN/) warped onto those of the range's first frame (the reference: written as it
// is) into TAKE/derived/textures-stable/frame-NNNNNN/ (the same files, wrinkle.exr with the U-Net, metrics.json with
// the mean flow and the albedo's jitter to the frame before, as fused and stabilized), run.json at the root (with the
// U-Net, its losses as loss.csv). The U-Net first reads every frame's albedo (at its resolution) and trains on them.
struct StabilizeJob {
  std::string take_dir;
  // Frames [first_frame, last_frame); last_frame < 0: up to the last the textures hold without a gap.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // Where the textures are and the results go, relative to the take or absolute; empty: derived/textures and
  // derived/textures-stable.
  std::string textures_dir, output_dir;
  StabilizeOptions options;

  absl::Status Validate() const;
};

absl::StatusOr<JobResult> RunStabilize(const StabilizeJob& job,
                                       const std::function<void(const JobProgress&)>& progress = {},
                                       const std::function<bool()>& cancelled = {});

}  // namespace stage::processing
