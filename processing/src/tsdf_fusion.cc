// Fusion of multi-view stereo's depth maps (mvs_internal.h) in Open3D's tensor VoxelBlockGrid: a truncated signed
// distance and a weight per voxel in hashed blocks of 16^3 voxels, integrated view by view (millimetres throughout:
// depth scale 1), then meshed by marching cubes where the weight (views) reaches options.min_views. The only source
// that includes Open3D, whose headers are heavy.
#include <omp.h>
#include <open3d/core/Tensor.h>
#include <open3d/t/geometry/Image.h>
#include <open3d/t/geometry/TriangleMesh.h>
#include <open3d/t/geometry/VoxelBlockGrid.h>

#include <algorithm>
#include <cstdlib>
#include <exception>
#include <mutex>
#include <numeric>
#include <tuple>

#include "absl/strings/str_cat.h"
#include "mvs_internal.h"

namespace stage::processing {

namespace core = open3d::core;
namespace tg = open3d::t::geometry;

namespace {

TriangleMesh CanonicalOrder(const TriangleMesh& in) {
  const size_t n = in.positions.size();
  std::vector<int32_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  auto key = [&](int32_t i) {
    const Eigen::Vector3f& p = in.positions[i];
    return std::make_tuple(p.x(), p.y(), p.z(), i);
  };
  std::sort(order.begin(), order.end(), [&](int32_t a, int32_t b) { return key(a) < key(b); });
  TriangleMesh out;
  std::vector<int32_t> rank(n);
  for (size_t i = 0; i < n; ++i) {
    rank[order[i]] = static_cast<int32_t>(i);
    out.positions.push_back(in.positions[order[i]]);
  }
  for (const auto& t : in.triangles) {
    std::array<int32_t, 3> r = {rank[t[0]], rank[t[1]], rank[t[2]]};
    // The smallest first, the winding kept.
    std::rotate(r.begin(), std::min_element(r.begin(), r.end()), r.end());
    out.triangles.push_back(r);
  }
  std::sort(out.triangles.begin(), out.triangles.end());
  return out;
}

absl::StatusOr<TriangleMesh> Fuse(const std::vector<MvsView>& views, const std::vector<DepthMap>& depths,
                                  double voxel_mm, const MvsOptions& options) {
  const core::Device cpu("CPU:0");
  // Open3D's kernels run OpenMP loops on every core unless OMP_NUM_THREADS is set (then on omp_get_max_threads()).
  // On a busy machine OpenMP's spinning threads slow them several times (measured: fusion 0.7 s on one thread, 2.7-5.9
  // s on two with both cores loaded), and fusion is a small share of the work: one thread, set here.
  static std::once_flag once;
  std::call_once(once, [] {
    if (std::getenv("OMP_NUM_THREADS") == nullptr) setenv("OMP_NUM_THREADS", "1", 0);
  });
  omp_set_num_threads(1);
  const float trunc = static_cast<float>(options.truncation_voxels);
  // Depths beyond the far side of the head's volume from the furthest camera are not surface.
  double depth_max = 0;
  for (const MvsView& v : views) {
    depth_max = std::max(depth_max, (v.position - options.volume_centre_mm).norm() + options.volume_radius_mm);
  }
  try {
    // Blocks for the head's surface: its area over a block's face, with room for the truncation band.
    const double block_mm = 16 * voxel_mm;
    const int64_t blocks = static_cast<int64_t>(
        std::clamp(12.0 * options.volume_radius_mm * options.volume_radius_mm / (block_mm * block_mm), 1e4, 4e6));
    tg::VoxelBlockGrid grid({"tsdf", "weight"}, {core::Float32, core::Float32}, {{1}, {1}},
                            static_cast<float>(voxel_mm), 16, blocks, cpu);
    for (size_t i = 0; i < views.size(); ++i) {
      const MvsView& v = views[i];
      const DepthMap& d = depths[i];
      if (std::none_of(d.depth.begin(), d.depth.end(), [](float z) { return z > 0; })) continue;
      // Open3D floors a voxel's projection to find its pixel: pixel centres at integers are half a pixel on.
      const core::Tensor intrinsic =
          core::Tensor::Init<double>({{v.fx, 0, v.cx + 0.5}, {0, v.fy, v.cy + 0.5}, {0, 0, 1}}, cpu);
      core::Tensor extrinsic = core::Tensor::Eye(4, core::Float64, cpu);
      const Eigen::Vector3d t = -v.rotation * v.position;
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) extrinsic[r][c] = v.rotation(r, c);
        extrinsic[r][3] = t(r);
      }
      const tg::Image depth(core::Tensor(d.depth, {d.height, d.width, 1}, core::Float32, cpu));
      const core::Tensor coords =
          grid.GetUniqueBlockCoordinates(depth, intrinsic, extrinsic, 1.0f, static_cast<float>(depth_max), trunc);
      grid.Integrate(coords, depth, intrinsic, extrinsic, 1.0f, static_cast<float>(depth_max), trunc);
    }
    const tg::TriangleMesh mesh = grid.ExtractTriangleMesh(static_cast<float>(options.min_views), -1);
    TriangleMesh out;
    if (!mesh.HasVertexPositions() || !mesh.HasTriangleIndices()) return out;
    const core::Tensor p = mesh.GetVertexPositions().To(core::Float32).Contiguous();
    const core::Tensor t = mesh.GetTriangleIndices().To(core::Int64).Contiguous();
    const float* pp = p.GetDataPtr<float>();
    const int64_t* tp = t.GetDataPtr<int64_t>();
    out.positions.resize(p.GetLength());
    for (int64_t i = 0; i < p.GetLength(); ++i) out.positions[i] = {pp[3 * i], pp[3 * i + 1], pp[3 * i + 2]};
    out.triangles.resize(t.GetLength());
    for (int64_t i = 0; i < t.GetLength(); ++i) {
      out.triangles[i] = {static_cast<int32_t>(tp[3 * i]), static_cast<int32_t>(tp[3 * i + 1]),
                          static_cast<int32_t>(tp[3 * i + 2])};
    }
    // Open3D's hash map hands blocks out in an order that changes from run to run: vertices sorted by position and
    // triangles by their vertices, so the same depth maps write the same file.
    return CanonicalOrder(out);
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("fusing the depth maps (Open3D): ", e.what()));
  }
}

}  // namespace
}  // namespace stage::processing

extern "C" __attribute__((visibility("default"))) stage::processing::FuseDepthMapsFn StageFuseDepthMaps() {
  return &stage::processing::Fuse;
}
