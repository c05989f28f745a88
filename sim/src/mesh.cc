// Triangle meshes as subjects of the simulated stage.
#include "stage/sim/mesh.h"

#include <Eigen/Geometry>
#include <cmath>

namespace stage::sim {

bool TriangleTangents(const Eigen::Vector3f& e1, const Eigen::Vector3f& e2, const Eigen::Vector2f& d1,
                      const Eigen::Vector2f& d2, Eigen::Vector3f* pu, Eigen::Vector3f* pv) {
  const float det = d1.x() * d2.y() - d2.x() * d1.y();
  if (std::abs(det) <= 1e-12f) return false;
  *pu = (e1 * d2.y() - e2 * d1.y()) / det;
  *pv = (e2 * d1.x() - e1 * d2.x()) / det;
  return true;
}

Eigen::Vector3f DetailedNormal(const Eigen::Vector3f& n, const Eigen::Vector3f& pu, const Eigen::Vector3f& pv,
                               const SurfaceSample& s) {
  const bool mapped = s.tangent_normal != Eigen::Vector3f::UnitZ();
  if (s.dh_du == 0 && s.dh_dv == 0 && !mapped) return n;
  // Project the tangents on the shading normal's plane so the detail rides on the smooth surface.
  Eigen::Vector3f tu = pu - n * n.dot(pu), tv = pv - n * n.dot(pv);
  Eigen::Vector3f detailed;
  if (mapped) {
    // Normal map: the tangent frame (u, v orthogonalized, n), whatever side the ray came from.
    tu.normalize();
    tv = (tv - tu * tu.dot(tv)).normalized();
    detailed = s.tangent_normal.x() * tu + s.tangent_normal.y() * tv + s.tangent_normal.z() * n;
  } else {
    // Bump mapping: the tangents tilted by the height's slope.
    detailed = (tu + s.dh_du * n).cross(tv + s.dh_dv * n);
    if (detailed.dot(n) < 0) detailed = -detailed;
  }
  if (detailed.squaredNorm() == 0) return n;
  return detailed.normalized();
}

MeshSubject::MeshSubject(TriangleMesh mesh, SurfaceFunction surface, bool convex)
    : bvh_(std::move(mesh)), surface_(std::move(surface)), normals_(bvh_.mesh().VertexNormals()), convex_(convex) {}

Hit MeshSubject::Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const {
  Hit hit;
  MeshHit where;
  if (!bvh_.Nearest(origin, direction, INFINITY, &where)) return hit;
  const TriangleMesh& mesh = bvh_.mesh();
  const int32_t tri = where.triangle;
  const float t = where.t, b1 = where.b1, b2 = where.b2;
  const auto& tr = mesh.triangles[tri];
  const float b0 = 1 - b1 - b2;
  const Eigen::Vector3f& p0 = mesh.positions[tr[0]];
  const Eigen::Vector3f e1 = mesh.positions[tr[1]] - p0, e2 = mesh.positions[tr[2]] - p0;
  hit.hit = true;
  hit.t = t;
  hit.point = origin + t * direction;
  Eigen::Vector3f g = e1.cross(e2).normalized();
  Eigen::Vector3f n = (b0 * normals_[tr[0]] + b1 * normals_[tr[1]] + b2 * normals_[tr[2]]).normalized();
  // Face the viewer (a ray may see the inside of an open mesh).
  if (g.dot(direction) > 0) {
    g = -g;
    n = -n;
  }
  if (n.dot(g) < 0.05f) n = g;
  hit.geometric_normal = g;
  hit.part = mesh.parts.empty() ? 0 : mesh.parts[tri];
  if (!mesh.uvs.empty()) {
    const Eigen::Vector2f &t0 = mesh.uvs[tr[0]], &t1 = mesh.uvs[tr[1]], &t2 = mesh.uvs[tr[2]];
    hit.uv = b0 * t0 + b1 * t1 + b2 * t2;
    if (surface_) {
      const SurfaceSample s = surface_(hit.uv, hit.part);
      hit.material = s.material;
      const Eigen::Vector2f d1 = t1 - t0, d2 = t2 - t0;
      Eigen::Vector3f pu, pv;
      if (TriangleTangents(e1, e2, d1, d2, &pu, &pv)) {
        const Eigen::Vector3f detailed = DetailedNormal(n, pu, pv, s);
        if (detailed.dot(g) > 0.05f) n = detailed;
      }
    }
  }
  hit.normal = n;
  return hit;
}

bool MeshSubject::AlbedoAt(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction,
                           Eigen::Vector3f* albedo) const {
  MeshHit where;
  if (!bvh_.Nearest(origin, direction, INFINITY, &where)) return false;
  const TriangleMesh& mesh = bvh_.mesh();
  // As Intersect finds it: the surface's at the point's texture coordinates, else the default material's.
  if (mesh.uvs.empty() || !surface_) {
    *albedo = Material{}.albedo;
    return true;
  }
  const auto& tr = mesh.triangles[where.triangle];
  const float b1 = where.b1, b2 = where.b2, b0 = 1 - b1 - b2;
  const Eigen::Vector2f uv = b0 * mesh.uvs[tr[0]] + b1 * mesh.uvs[tr[1]] + b2 * mesh.uvs[tr[2]];
  *albedo = surface_(uv, mesh.parts.empty() ? 0 : mesh.parts[where.triangle]).material.albedo;
  return true;
}

bool MeshSubject::Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const {
  return bvh_.Occluded(from, to);
}

void MeshSubject::OccludedMany(std::span<const Eigen::Vector3f> from, std::span<const Eigen::Vector3f> to,
                               std::span<uint8_t> blocked) const {
  bvh_.Occluded(from, to, blocked);
}

}  // namespace stage::sim
