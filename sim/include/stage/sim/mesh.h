// Triangle meshes as subjects (stage/common/mesh.h has the mesh, its hierarchy and OBJ files): per-vertex normals,
// and a material that may vary over the texture (skin maps, detail normals from a height field).
#pragma once

#include <Eigen/Core>
#include <functional>
#include <vector>

#include "stage/common/mesh.h"
#include "stage/sim/subject.h"

namespace stage::sim {

// What the surface is like at texture coordinate `uv` of part `part`: its material, and its detail height (mm, along
// the normal) with the derivatives in u and v, for bump mapping. Must be thread-safe.
// A normal map may give the detail instead: the normal in the tangent frame (x along +u, y along +v, z out).
struct SurfaceSample {
  Material material;
  float height = 0;
  float dh_du = 0, dh_dv = 0;
  Eigen::Vector3f tangent_normal = Eigen::Vector3f::UnitZ();
};
using SurfaceFunction = std::function<SurfaceSample(const Eigen::Vector2f& uv, int part)>;

// A triangle's tangents dP/du and dP/dv from its edges e1 = p1 - p0, e2 = p2 - p0 and their texture coordinates
// d1 = t1 - t0, d2 = t2 - t0; false where its texture coordinates are degenerate.
bool TriangleTangents(const Eigen::Vector3f& e1, const Eigen::Vector3f& e2, const Eigen::Vector2f& d1,
                      const Eigen::Vector2f& d2, Eigen::Vector3f* pu, Eigen::Vector3f* pv);

// The shading normal of a surface whose smooth normal is `n` (unit) and whose tangents are `pu`, `pv`, with the
// detail `s` brings (its height's slope, or its tangent-space normal); `n` where it brings none. What the renderer
// shades with (where the result is not turned away from the triangle's own normal).
Eigen::Vector3f DetailedNormal(const Eigen::Vector3f& n, const Eigen::Vector3f& pu, const Eigen::Vector3f& pv,
                               const SurfaceSample& s);

class MeshSubject final : public Subject {
 public:
  // Builds the hierarchy (median splits, 4 triangles a leaf). `surface` null: the default Material, no detail.
  // `convex`: the maker vouches that no part of the mesh can shadow another (Subject::Convex).
  MeshSubject(TriangleMesh mesh, SurfaceFunction surface, bool convex = false);
  Hit Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const override;
  bool AlbedoAt(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction,
                Eigen::Vector3f* albedo) const override;
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const override;
  void OccludedMany(std::span<const Eigen::Vector3f> from, std::span<const Eigen::Vector3f> to,
                    std::span<uint8_t> blocked) const override;
  bool Convex() const override { return convex_; }
  const TriangleMesh& mesh() const { return bvh_.mesh(); }

 private:
  MeshBvh bvh_;
  SurfaceFunction surface_;
  std::vector<Eigen::Vector3f> normals_;
  bool convex_ = false;
};

}  // namespace stage::sim
