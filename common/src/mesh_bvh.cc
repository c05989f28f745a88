// Rays through triangle meshes: Embree's hierarchy and intersectors (docs/dependencies.md says why not our own).
#include <embree3/rtcore.h>

#include <cstdlib>
#include <cstring>
#include <limits>
#include <vector>

#include "stage/common/logging.h"
#include "stage/common/mesh.h"

namespace stage {
namespace {

// The process's one Embree device: its kernels picked for this CPU once, its build threads shared by every mesh.
// Embree reports errors through the callback; a device that cannot be made is a broken install, not bad input.
RTCDevice Device() {
  static RTCDevice device = [] {
    RTCDevice d = rtcNewDevice(nullptr);
    if (d == nullptr) {
      Logger("geometry")->critical("Embree: no device ({})", static_cast<int>(rtcGetDeviceError(nullptr)));
      std::abort();
    }
    rtcSetDeviceErrorFunction(
        d,
        [](void*, RTCError code, const char* what) {
          Logger("geometry")->error("Embree error {}: {}", static_cast<int>(code), what != nullptr ? what : "");
        },
        nullptr);
    return d;
  }();
  return device;
}

// A ray from `o` along `d` within (tnear, tfar), every mask bit set (Debian's Embree tests ray masks: a ray whose
// mask is 0 meets nothing).
RTCRay MakeRay(const Eigen::Vector3f& o, const Eigen::Vector3f& d, float tnear, float tfar) {
  RTCRay ray;
  ray.org_x = o.x();
  ray.org_y = o.y();
  ray.org_z = o.z();
  ray.tnear = tnear;
  ray.dir_x = d.x();
  ray.dir_y = d.y();
  ray.dir_z = d.z();
  ray.time = 0;
  ray.tfar = tfar;
  ray.mask = std::numeric_limits<unsigned>::max();
  ray.id = 0;
  ray.flags = 0;
  return ray;
}

// Embree reports a failed call (out of memory, a buffer it could not make, a build that failed) only through its
// error code; a scene left half built would miss rays without a word, so the process stops and says what failed.
void StopOnEmbreeError(const char* what, size_t triangles) {
  if (const RTCError e = rtcGetDeviceError(Device()); e != RTC_ERROR_NONE) {
    Logger("geometry")
        ->critical("Embree could not {} for a mesh of {} triangles (error {})", what, triangles, static_cast<int>(e));
    std::abort();
  }
}

// Where a hit closer than this is the ray's own surface (the shadow rays' start is lifted 1e-3 mm off it).
constexpr float kNear = 1e-4f;

// The occlusion ray of the segment from `from` to `to`; inactive (tnear > tfar: Embree traces nothing, and nothing
// blocks it) where the segment is too short to trace.
RTCRay SegmentRay(const Eigen::Vector3f& from, const Eigen::Vector3f& to) {
  const Eigen::Vector3f d = to - from;
  const float len = d.norm();
  return len > kNear ? MakeRay(from, d / len, kNear, len) : MakeRay(from, Eigen::Vector3f::UnitZ(), 1, 0);
}

}  // namespace

struct MeshBvh::Scene {
  explicit Scene(TriangleMesh m) : mesh(std::move(m)) {}
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;
  ~Scene() {
    if (scene != nullptr) rtcReleaseScene(scene);
  }
  TriangleMesh mesh;
  RTCScene scene = nullptr;
};

MeshBvh::MeshBvh(TriangleMesh mesh) {
  auto s = std::make_shared<Scene>(std::move(mesh));
  const TriangleMesh& m = s->mesh;
  s->scene = rtcNewScene(Device());
  // Robust: no ray slips between two triangles that share an edge (a shadow ray through a closed head would light
  // its inside).
  rtcSetSceneFlags(s->scene, RTC_SCENE_FLAG_ROBUST);
  if (!m.triangles.empty()) {
    RTCGeometry g = rtcNewGeometry(Device(), RTC_GEOMETRY_TYPE_TRIANGLE);
    // Embree's own buffers (padded as its vector loads need), filled from the mesh.
    auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                          3 * sizeof(float), m.positions.size()));
    auto* t = static_cast<uint32_t*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                             3 * sizeof(uint32_t), m.triangles.size()));
    StopOnEmbreeError("make its buffers", m.triangles.size());
    for (size_t i = 0; i < m.positions.size(); ++i) std::memcpy(v + 3 * i, m.positions[i].data(), 3 * sizeof(float));
    for (size_t i = 0; i < m.triangles.size(); ++i) {
      for (int k = 0; k < 3; ++k) t[3 * i + k] = static_cast<uint32_t>(m.triangles[i][k]);
    }
    rtcCommitGeometry(g);
    rtcAttachGeometry(s->scene, g);
    rtcReleaseGeometry(g);
  }
  rtcCommitScene(s->scene);
  StopOnEmbreeError("build the hierarchy", m.triangles.size());
  scene_ = std::move(s);
}

const TriangleMesh& MeshBvh::mesh() const { return scene_->mesh; }

bool MeshBvh::Nearest(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, float tmax, MeshHit* hit) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRayHit rh;
  rh.ray = MakeRay(origin, direction, kNear, tmax);
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(scene_->scene, &context, &rh);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  hit->triangle = static_cast<int32_t>(rh.hit.primID);
  hit->t = rh.ray.tfar;
  hit->b1 = rh.hit.u;
  hit->b2 = rh.hit.v;
  return true;
}

bool MeshBvh::Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const {
  RTCRay ray = SegmentRay(from, to);
  if (ray.tnear > ray.tfar) return false;
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  rtcOccluded1(scene_->scene, &context, &ray);
  // Embree marks an occluded ray by setting its tfar to -inf.
  return ray.tfar < 0;
}

void MeshBvh::Occluded(std::span<const Eigen::Vector3f> from, std::span<const Eigen::Vector3f> to,
                       std::span<uint8_t> blocked) const {
  if (from.size() != to.size() || from.size() != blocked.size()) {
    Logger("geometry")
        ->critical("MeshBvh::Occluded: {} starts, {} ends, {} answers", from.size(), to.size(), blocked.size());
    std::abort();
  }
  // Reused by the thread's later calls (a renderer asks a few thousand at a time).
  thread_local std::vector<RTCRay> rays;
  rays.resize(from.size());
  for (size_t i = 0; i < from.size(); ++i) rays[i] = SegmentRay(from[i], to[i]);
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  rtcOccluded1M(scene_->scene, &context, rays.data(), static_cast<unsigned>(rays.size()), sizeof(RTCRay));
  for (size_t i = 0; i < rays.size(); ++i) blocked[i] = rays[i].tfar < 0 ? 1 : 0;
}

}  // namespace stage
