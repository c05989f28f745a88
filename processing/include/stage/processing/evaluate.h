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
  // Split the figures by the geometry each pixel was solved with (geometry_depth.exr and geometry_placed.png, written
  // with --geometry): that of these results (empty), or of another run's results directory, so that two runs (the
  // true mesh's and a reconstruction's) are judged over the same pixels. Results solved without geometry are not
  // split unless this names a run that had it.
  std::string geometry_from;
  // A point (on the mesh or placed beyond it) this far from the truth's surface (camera-frame z, mm) or farther is
  // counted as off it. > 0.
  double geometry_off_mm = 0.5;

  // InvalidArgument naming the field.
  absl::Status Validate() const;
};

// Where a pixel's point came from when it was solved (EvaluateOptions::geometry_from).
enum class GeometryClass : uint8_t {
  kOnMesh = 0,  // the mesh, within geometry_off_mm of the truth
  kOffMesh,     // the mesh, geometry_off_mm or more from the truth
  kPlacedOn,    // placed beyond the mesh (FillGeometry, RefillGeometry), within geometry_off_mm of the truth
  kPlacedOff,   // placed beyond the mesh, geometry_off_mm or more from the truth
  kNone,        // no point: the units seen from the stage origin
};
constexpr int kGeometryClasses = 5;
const char* GeometryClassName(GeometryClass c);

struct GeometrySplit {
  GeometryClass geometry = GeometryClass::kNone;
  int64_t mask_pixels = 0;        // of the subject mask
  double depth_error_median = 0;  // |z - the truth's z| (mm), median; 0 for kNone
  struct Map {
    int64_t pixels = 0;  // compared
    double mean = 0, median = 0;
    double share = 0;  // of the map's summed error over all pixels (0..1)
  };
  std::vector<Map> maps;  // in Evaluation::maps' order
};

struct Evaluation {
  int64_t units = 0;  // camera frames compared
  int64_t mask_pixels = 0;
  std::vector<MapError> maps;
  std::string geometry_from;               // the run the split's classes came from; empty: not split
  std::vector<GeometrySplit> by_geometry;  // one per GeometryClass, when split
};

absl::StatusOr<Evaluation> EvaluatePhotometric(const EvaluateOptions& options);

// The table people read, and JSON for scripts.
std::string FormatEvaluation(const Evaluation& e);
std::string EvaluationJson(const Evaluation& e);

}  // namespace stage::processing
