// Multi-view stereo's meshes against the simulator's ground truth (docs/geometry.md#evaluation): per frame, the
// distance of every reconstructed vertex to the true surface (accuracy: RMSE, median, 95th percentile) and the share
// of the true surface within 1 mm of the reconstruction (completeness) and the share the reconstruction covers (its
// holes: the true normal meets no reconstruction within 1 mm), over the surface at least two machine-vision
// cameras see at less than 60 degrees from its normal, with the face, the eyes, the mouth and the rest of the skin
// apart.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/mesh.h"
#include "stage/processing/calibrate.h"

namespace stage::processing {

// Distances from points to a triangle mesh's surface (exact point-to-triangle distance over the triangles nearest by
// their centres, found in a k-d tree). Thread-safe once built.
class SurfaceDistance {
 public:
  explicit SurfaceDistance(const TriangleMesh& mesh);
  ~SurfaceDistance();
  SurfaceDistance(const SurfaceDistance&) = delete;
  SurfaceDistance& operator=(const SurfaceDistance&) = delete;
  // The distance from `p` to the surface, mm, and the triangle it is nearest (-1: an empty mesh).
  float Distance(const Eigen::Vector3f& p, int32_t* triangle = nullptr) const;
  // The point of the surface nearest `p` and its triangle (-1, and `p` itself: an empty mesh).
  Eigen::Vector3f Closest(const Eigen::Vector3f& p, int32_t* triangle = nullptr) const;

 private:
  struct Index;
  const TriangleMesh& mesh_;
  Index* index_;
};

// Where on the simulated head a true triangle is: the face's skin (chin to forehead, the front 150 degrees), the eyes,
// the mouth (lips and opening), and the rest of the skin (scalp, neck, the back of the head).
enum class HeadRegion { kFace = 0, kEyes = 1, kMouth = 2, kOtherSkin = 3 };
inline constexpr int kHeadRegions = 4;
const char* HeadRegionName(HeadRegion r);

struct MvsRegionError {
  HeadRegion region = HeadRegion::kFace;
  int64_t vertices = 0;  // reconstructed vertices nearest to this region's seen surface
  double rmse_mm = 0, median_mm = 0, p95_mm = 0;
  double seen_area_mm2 = 0;  // the true surface of the region at least two cameras see
  double completeness = 0;   // share of it within `within_mm` of the reconstruction
  // Share of it where the line along its normal meets the reconstruction within +-within_mm: what is not a hole
  // (completeness counts a point beside a small hole as near the surface).
  double coverage = 0;
  // The distance of the mesh's triangle centres to the true surface, RMS weighted by area: the surface as well as
  // its vertices (a filled hole's patch adds triangles, no vertex).
  double surface_rmse_mm = 0;
};

struct MvsEvaluateOptions {
  std::string take_dir;
  int64_t first_frame = 0;
  int64_t last_frame = -1;  // < 0: every frame with results
  std::string results_dir;  // empty: <take>/derived/mvs
  std::string truth_dir;    // empty: <take>/ground_truth (its cameras.json places the cameras that see)
  double within_mm = 1;     // completeness: true surface within this of the reconstruction
  // The true surface counts where this many machine-vision cameras see it (in their image, unoccluded), each at less
  // than max_view_angle_deg from its normal (grazing views show stereo nothing to match). Defaults 2 and 60.
  int min_cameras = 2;
  double max_view_angle_deg = 60;
  absl::Status Validate() const;
};

struct MvsEvaluation {
  int64_t frames = 0;
  int64_t vertices = 0, unseen_vertices = 0;  // reconstructed; nearest to true surface no two cameras see
  double within_mm = 1;
  std::vector<MvsRegionError> regions;  // by HeadRegion
  // The views' depth maps against the truth's (at the recorded size), where both have one: signed and absolute.
  int64_t depth_pixels = 0;
  double depth_median_mm = 0, depth_median_abs_mm = 0;
  // The meshes are in the frame of the cameras that made them; a calibration fixes its frame only up to a rigid
  // motion (the rig's nominal frame), so they are moved into the truth's first, by the motion under which those
  // cameras see the head's volume most nearly as the true ones do (CompareCalibrations). What placed the cameras
  // (the results' run.json), and that motion's translation and angle.
  std::string cameras_placed_by;
  double frame_offset_mm = 0, frame_rotation_deg = 0;
};

absl::StatusOr<MvsEvaluation> EvaluateMvs(const MvsEvaluateOptions& options);

// The calibration a run placed its cameras with (`results`/run.json's "calibration": a file or directory in the take,
// or empty for the rig's nominal models) against the truth's cameras: the motion from its frame to the truth's.
// `placed_by` (optional): the run's "cameras_placed_by", or the calibration named. Errors name the run's file.
absl::StatusOr<TruthComparison> RunFrameToTruth(const std::string& take_dir, const std::string& results,
                                                const CameraCalibration& truth, std::string* placed_by = nullptr);

// Pictures of a frame's mesh as `camera` (placed as the truth says) sees it, at most 1024 pixels wide:
// <out_prefix>-mesh.png (shaded by its facets' angle to the camera) and <out_prefix>-error.png (each visible point's
// distance to the true surface, colour map turbo from 0 to error_range_mm; grey: no mesh).
absl::Status WriteMvsPictures(const std::string& take_dir, const std::string& results_dir, int64_t frame,
                              const std::string& camera, const std::string& out_prefix, double error_range_mm = 1);
std::string FormatMvsEvaluation(const MvsEvaluation& e);
std::string MvsEvaluationJson(const MvsEvaluation& e);

}  // namespace stage::processing
