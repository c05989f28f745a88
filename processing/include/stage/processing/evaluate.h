// Photometric results against the simulator's ground truth (docs/processing.md#evaluation): every map of every
// processed frame and camera compared with <take>/ground_truth on the subject mask (pixels the subject fills), per
// map the mean and median error, and the same restricted to a high-pass band (detail finer than a few pixels: pores,
// fine wrinkles) beside what an estimate without any such detail would score there, so that smoothing cannot pass
// for accuracy.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace stage::processing {

struct MapError {
  std::string map;      // "diffuse normal", "specular normal", "albedo", "specular intensity", "roughness"
  std::string metric;   // "angle (deg)", "relative (%)", "absolute"
  int64_t pixels = 0;   // compared (the mask, where the map has a value)
  double coverage = 0;  // pixels / mask pixels
  double mean = 0, median = 0;
  // In the band: the error of the map's high-pass part, and the truth's own high-pass part (the error of an estimate
  // with no detail at all).
  double band_mean = 0, band_median = 0, band_floor = 0;
  // The same over the confident pixels only: those the solver flagged neither saturated, bad fit, shadowed nor
  // implausible (and for the specular maps, not a bad lobe fit); `left_out` is how many of `pixels` that leaves out.
  int64_t confident_pixels = 0;
  int64_t left_out = 0;
  double confident_mean = 0, confident_median = 0;
};

struct EvaluateOptions {
  std::string take_dir;
  int64_t first_frame = 0;
  int64_t last_frame = -1;           // < 0: every frame with results
  std::vector<std::string> cameras;  // empty: every camera with results
  std::string results_dir;           // empty: <take>/derived/photometric
  std::string truth_dir;             // empty: <take>/ground_truth
  // The band: detail finer than a Gaussian of this sigma (pixels).
  double band_sigma_px = 2;
};

struct Evaluation {
  int64_t units = 0;  // camera frames compared
  int64_t mask_pixels = 0;
  std::vector<MapError> maps;
};

absl::StatusOr<Evaluation> EvaluatePhotometric(const EvaluateOptions& options);

// The table people read, and JSON for scripts.
std::string FormatEvaluation(const Evaluation& e);
std::string EvaluationJson(const Evaluation& e);

}  // namespace stage::processing
