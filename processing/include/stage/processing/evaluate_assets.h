// The UV assets against the simulator's ground truth (docs/assets.md#evaluation), per frame:
// - the fit (TAKE/derived/fit): every template vertex against where the head's layout puts its skin point on the
//   true posed mesh (EvaluateFit), skin, eyes and mouth apart, sliding along the surface apart from distance to it;
//   a fit to multi-view stereo's meshes is moved into the truth's frame first (the calibration's frame is the rig's
//   nominal one up to a rigid motion: RunFrameToTruth);
// - the fused textures (TAKE/derived/textures): the truth's per-camera maps (TAKE/ground_truth/frame-N/CAMERA/)
//   fused through the same fitted mesh and cameras with the photometric solve's own weights (its confidence, the
//   pixels it solved, the lobes it measured), against the textures fused from the solve (CompareTextures), over every
//   covered texel and over those two or more views see. The textures on disk must be what fusion makes of the
//   solve's maps (checked: the albedo bit for bit), so the figures are the files'.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/texture_fusion.h"

namespace stage::processing {

struct AssetsEvaluateOptions {
  std::string take_dir;
  int64_t first_frame = 0;
  int64_t last_frame = -1;  // < 0: every frame with results
  bool fit = true;          // evaluate the fit
  bool textures = true;     // evaluate the fused textures
  // Where the results and the truth are, relative to the take or absolute; empty: derived/fit, derived/textures,
  // ground_truth.
  std::string fit_dir, textures_dir, truth_dir;

  absl::Status Validate() const;
};

struct FrameAssetsEvaluation {
  int64_t frame = 0;
  bool has_fit = false, has_textures = false;
  FitEvaluation fit;
  TextureErrors textures;          // every covered texel
  TextureErrors textures_overlap;  // texels two or more views see
};

struct AssetsEvaluation {
  std::vector<FrameAssetsEvaluation> frames;
  // The fit's surfaces and the frame it was moved by into the truth's (0 for the truth's own surfaces).
  std::string fit_surface;
  double frame_offset_mm = 0, frame_rotation_deg = 0;
};

absl::StatusOr<AssetsEvaluation> EvaluateAssets(const AssetsEvaluateOptions& options);
std::string FormatAssetsEvaluation(const AssetsEvaluation& e);
std::string AssetsEvaluationJson(const AssetsEvaluation& e);

}  // namespace stage::processing
