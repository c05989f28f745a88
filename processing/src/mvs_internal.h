// Multi-view stereo's steps (mvs.h), apart so that tests can run them one by one: the views' neighbours, each view's
// depth by a coarse-to-fine sweep, the filter by agreement across views, fusion and meshing (the one file that
// includes Open3D: tsdf_fusion.cc) and the trim to the head.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/mesh.h"
#include "stage/processing/light_model.h"
#include "stage/processing/mvs.h"
#include "stage/processing/take_frames.h"

namespace stage::processing {

// A camera of a job: its frame file and its model at the recorded size.
using MvsCamera = TakeCamera;

// A job's take opened for reading (RunMvs, mvs_bench): its light model, the calibration the job names, its cameras
// (the job's, or every machine-vision camera) placed by it, and the frames they recorded.
struct MvsTake {
  LightModel light;
  std::optional<CameraCalibration> calibration;
  std::vector<MvsCamera> cameras;
  int64_t frames = 0;
};
absl::StatusOr<MvsTake> OpenMvsTake(const MvsJob& job);

// A frame's views as read: the views, each one's camera at the processing size, and the cameras without a frame.
struct FrameViews {
  std::vector<MvsView> views;
  std::vector<CameraModel> processed;
  std::vector<std::string> missing;
};
// Frame `frame`'s full-lit views of `take`'s cameras at `scale` (MakeMvsView); errors name the file.
absl::Status ReadFrameViews(const MvsTake& take, int64_t frame, double scale, FrameViews* out);

// For every view, the indices of its neighbours (options.neighbours at most, nearest first by the angle between
// optical axes within [min_angle_deg, max_angle_deg]).
std::vector<std::vector<int>> ChooseNeighbours(const std::vector<MvsView>& views, const MvsOptions& options);

// View `ref`'s depth from its neighbours `neighbours`, coarse to fine; `metrics` gets foreground and matched.
DepthMap SweepDepth(const std::vector<MvsView>& views, int ref, const std::vector<int>& neighbours,
                    const MvsOptions& options, MvsViewMetrics* metrics);

// Clears the depths of view `ref` that fewer than options.min_consistent of its neighbours' maps agree with.
// Returns the depths kept.
int64_t KeepConsistent(const std::vector<MvsView>& views, const std::vector<DepthMap>& depths, int ref,
                       const std::vector<int>& neighbours, const MvsOptions& options, DepthMap* out);

// The surface the depth maps agree on: fused into a truncated signed distance volume of `voxel_mm` voxels and meshed
// where at least options.min_views views saw it (stage frame, mm). By Open3D, in a module of its own that the first
// fusion opens (libstage_tsdf_fusion.so, tsdf_fusion.cc; stage/common/module.h): Open3D brings VTK and 45 more
// libraries, 104,750 symbol relocations, into the start of every processing program, and only MVS fuses.
absl::StatusOr<TriangleMesh> FuseDepthMaps(const std::vector<MvsView>& views, const std::vector<DepthMap>& depths,
                                           double voxel_mm, const MvsOptions& options);
using FuseDepthMapsFn = absl::StatusOr<TriangleMesh> (*)(const std::vector<MvsView>& views,
                                                         const std::vector<DepthMap>& depths, double voxel_mm,
                                                         const MvsOptions& options);
inline constexpr const char* kTsdfFusionTarget = "stage_tsdf_fusion";
inline constexpr const char* kTsdfFusionEntry = "StageFuseDepthMaps";  // returns a FuseDepthMapsFn

// The largest connected piece of `mesh` with its vertices inside the sphere (centre, radius); unused vertices dropped.
TriangleMesh TrimToHead(const TriangleMesh& mesh, const Eigen::Vector3d& centre, double radius_mm);

// Closes every hole of `mesh` at most max_width_mm wide (4 x its area over its boundary's length: a disc's diameter,
// a crack's width) and at most 5 times as long (0: none), by the triangles between its boundary's vertices of least
// area, no vertex added.
struct HoleFill {
  int64_t holes = 0;
  double area_mm2 = 0;
};
HoleFill FillHoles(double max_width_mm, TriangleMesh* mesh);

// Taubin's smoothing (lambda 0.5, mu -0.53, uniform weights over each vertex's ring), `iterations` pairs of steps:
// the fused surface's noise of a fraction of a voxel taken out without shrinking it.
void SmoothMesh(int iterations, TriangleMesh* mesh);

}  // namespace stage::processing
