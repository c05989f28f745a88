// Multi-view stereo as a stage of the pipeline (docs/geometry.md): per virtual frame, the full-lit images of the
// machine-vision cameras, undistorted with the calibration, give a depth map per view (a coarse-to-fine sweep along
// each neighbour's epipolar line, scored by zero-mean normalized cross-correlation, bounded at every finer level by
// the coarser level's surface), filtered by agreement across views, fused into a truncated signed distance volume
// (Open3D's VoxelBlockGrid) and meshed; the mesh is trimmed to the head. Writes
// <take>/derived/mvs/frame-NNNNNN/mesh.obj (stage frame, mm), depth/<camera>.exr and metrics.json. One code path for
// the library call, `stage-process mvs` and the ProcessingWorker job.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_model.h"
#include "stage/common/mesh.h"
#include "stage/processing/photometric.h"
#include "stage/processing/photometric_stage.h"

namespace stage::processing {

struct MvsOptions {
  // Processing resolution relative to the recorded images (1: as recorded; 0.5: half each way). Default 1.
  double image_scale = 1;
  // Views each view is matched against: the nearest by the angle between optical axes, within [min_angle_deg,
  // max_angle_deg]. Default 4, within 5-50 degrees.
  int neighbours = 4;
  double min_angle_deg = 5, max_angle_deg = 50;
  // A depth's score is the mean zero-mean normalized cross-correlation of its best `best_of` neighbours (a point
  // hidden from the others still scores). Default 2.
  int best_of = 2;
  // Side of the correlation window, pixels (odd). Default 7.
  int window = 7;
  // The coarsest level of the image pyramid is at most this wide, pixels; it sweeps the whole volume. Default 128.
  int coarse_width = 128;
  // At every finer level, depths within +-refine_steps steps (one step moves the point by at most a pixel in every
  // neighbour) of the coarser level's depth. Default 3.
  int refine_steps = 3;
  // Before a finer level sweeps about it, every depth of the coarser level is replaced by the median of the depths
  // within this radius (coarser pixels): a wrong coarse depth would otherwise steer the narrow sweep below it, and
  // the finer levels could not recover (docs/geometry.md). 0: none. Default 3.
  int prior_median_radius = 3;
  // A depth is kept where its score reaches this. Default 0.5.
  double min_score = 0.5;
  // Where a pixel covers less than fine_footprint_mm at the head (the median view's, at the volume's centre),
  // fine_min_score applies instead: a 7 x 7 window there holds too little of the skin's texture to score high, while
  // the agreement across views (2 pixel footprints) is strict enough to filter what the lower bar lets through
  // (docs/geometry.md). Defaults 0.3 below 0.35 mm (half resolution and finer on the shipped rig).
  double fine_min_score = 0.3;
  double fine_footprint_mm = 0.35;
  // Where a finer level finds no depth (too little texture in its window, or no score high enough), keep the coarser
  // level's (its windows cover more of the surface); the agreement across views then judges it. Default false:
  // the holes it fills come back noisier (docs/geometry.md).
  bool keep_coarser = false;
  // Pixels darker than this fraction of the image's 99th percentile are background. Default 0.04.
  double min_signal = 0.04;
  // Each view's silhouette (its pixels at or above the background's bar, holes closed; the visual hull's evidence,
  // written beside the mesh as silhouette/ID.png) is grown by this many pixels at the processing size: a margin for
  // the outline's own pixel. At most 16; default 1.
  int silhouette_grow_px = 1;
  // A depth is kept where at least `min_consistent` neighbours' depth maps put the same point within consistency_px
  // of their pixel footprint. Default 1 and 2 px.
  int min_consistent = 1;
  double consistency_px = 2;
  // The volume the head is in (the sweep's bounds and the mesh's trim): a sphere, stage frame, mm. Default the stage
  // origin, radius 200 mm.
  Eigen::Vector3d volume_centre_mm = Eigen::Vector3d::Zero();
  double volume_radius_mm = 200;
  // Voxel of the fused volume, mm; 0: `voxel_px` pixel footprints at the volume's centre (the median view's), at
  // least 0.2 mm. Defaults 0 and 1.
  double voxel_mm = 0;
  double voxel_px = 1;
  // Truncation of the signed distance, voxels. Default 4.
  double truncation_voxels = 4;
  // A surface is meshed where at least this many views saw it. Default 2.
  int min_views = 2;
  // Holes of the mesh at most this wide (4 x area over boundary length) and 5 times as long are closed, before the
  // smoothing, by the least-area triangles between their boundary's vertices; mm, 0: none. Default 4: the pinholes
  // left where no view matched (docs/geometry.md).
  double fill_holes_mm = 4;
  // Taubin smoothing of the mesh (mvs_internal.h): pairs of steps. Default 10.
  int smooth_iterations = 10;
  // Worker threads (views at a time). 0: one per core.
  int threads = 0;
  absl::Status Validate() const;
};

// One camera's image as multi-view stereo takes it: undistorted to a pinhole camera.
struct MvsView {
  std::string id;
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;                   // pixel centres at integers
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // stage -> camera (OpenCV's camera frame)
  Eigen::Vector3d position = Eigen::Vector3d::Zero();      // centre, stage frame, mm
  std::vector<float> grey;                                 // linear, width x height
};

// `grey` (recorded through `camera`, of the same size) resampled to `scale` of its size and undistorted: the pinhole
// camera of the same intrinsics at that size. InvalidArgument: sizes differ.
absl::StatusOr<MvsView> MakeMvsView(const std::string& id, const Image& grey, const CameraModel& camera, double scale);

// A view's depth: distance along its optical axis, mm; 0 where none. In the view's (undistorted) pixels.
struct DepthMap {
  int width = 0, height = 0;
  std::vector<float> depth;
  std::vector<float> score;  // the depth's correlation score
};

struct MvsViewMetrics {
  std::string id;
  std::vector<std::string> neighbours;
  int64_t foreground = 0;  // pixels with signal
  int64_t matched = 0;     // a depth scored above min_score
  int64_t consistent = 0;  // ... and agreed by the neighbours: what is fused
};

struct MvsFrame {
  TriangleMesh mesh;             // stage frame, mm
  std::vector<DepthMap> depths;  // per view, consistent depths only
  std::vector<MvsViewMetrics> views;
  double voxel_mm = 0;
  double pixel_mm = 0;   // a pixel's footprint at the volume's centre (the median view's)
  double min_score = 0;  // the bar the depths met (MvsOptions::min_score or fine_min_score)
  int64_t mesh_vertices_before_trim = 0;
  int64_t holes_filled = 0;  // FillHoles: holes closed and their area
  double filled_mm2 = 0;
  double depth_s = 0, fusion_s = 0, mesh_s = 0;  // wall time of each step
};

// The reconstruction of one frame from `views` (at least 2). Errors name the view.
absl::StatusOr<MvsFrame> ReconstructFrame(const std::vector<MvsView>& views, const MvsOptions& options);

struct MvsJob {
  // The take directory.
  std::string take_dir;
  // Virtual frames [first_frame, last_frame); last_frame < 0: every frame the take recorded.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // Camera ids; empty: every machine-vision camera of the take's rig.
  std::vector<std::string> cameras;
  // Where the cameras are (as PhotometricJob::calibration). Empty: the rig's nominal models (said so in run.json).
  std::string calibration;
  // Where the results go; empty: <take_dir>/derived/mvs.
  std::string output_dir;
  MvsOptions options;
};

// Runs the job; `progress` after each frame's views are read and after each frame; `cancelled` asked before each
// frame. Errors name the take, frame, camera or file.
absl::StatusOr<JobResult> RunMvs(const MvsJob& job, const std::function<void(const JobProgress&)>& progress = {},
                                 const std::function<bool()>& cancelled = {});

}  // namespace stage::processing
