// Temporal stabilization of fused UV textures, the optical-flow baseline (docs/assets.md#temporal-stabilization). A
// fit that slides along the skin moves the skin's texture about the UV layout from frame to frame: pores and freckles
// drift and the textures shimmer when played. Each frame's textures are warped onto a reference frame's (the neutral
// one) along the optical flow between the two albedos in UV space (OpenCV's DIS on the albedo's luminance); the other
// maps follow the same flow. The flow is smooth over its patches, so a wrinkle (a change of the normals, not of the
// albedo) is carried along, not flattened.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/processing/texture_fusion.h"

namespace stage::processing {

struct StabilizeOptions {
  // DIS's patch size and the stride between patches, texels (4..64, 1..patch_size).
  int patch_size = 12;
  int patch_stride = 4;
  // Variational refinement iterations per scale (0: none).
  int refinement_iterations = 5;
  // A flow longer than this, texels, is not trusted: the texel keeps its own value (> 0).
  double max_flow_px = 40;

  absl::Status Validate() const;
};

struct StabilizedTextures {
  FusedTextures textures;   // the frame's, on the reference's texels
  Image flow;               // 2 channels: where each reference texel is found in the frame, texels
  double mean_flow_px = 0;  // over the texels both cover
};

// `frame`'s textures warped onto `reference`'s texels. Errors: options out of range, textures of different sizes.
absl::StatusOr<StabilizedTextures> StabilizeTextures(const FusedTextures& reference, const FusedTextures& frame,
                                                     const StabilizeOptions& options);

// The albedo's jitter between two frames' textures (the FaStage paper's Fig. 17 measure): over the texels `a` and `b`
// both cover (and `mask` holds, if given), the mean of |la - lb| / ((la + lb) / 2), l the albedo's luminance.
double AlbedoJitter(const FusedTextures& a, const FusedTextures& b, const std::vector<bool>* mask = nullptr);

// The stage (docs/assets.md#temporal-stabilization): the fused textures of a take's frames
// (TAKE/derived/textures/frame-NNNNNN/) warped onto those of the range's first frame (the reference: written as it
// is) into TAKE/derived/textures-stable/frame-NNNNNN/ (the same files, metrics.json with the mean flow and the
// albedo's jitter to the frame before, as fused and stabilized), run.json at the root.
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
