// Triangle meshes as subjects: a bounding volume hierarchy for rays and shadow rays, per-vertex normals and texture
// coordinates, and a material that may vary over the texture (skin maps, detail normals from a height field).
#pragma once

#include <Eigen/Core>
#include <array>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/sim/subject.h"

namespace stage::sim {

struct TriangleMesh {
  std::vector<Eigen::Vector3f> positions;
  std::vector<Eigen::Vector2f> uvs;               // per vertex
  std::vector<std::array<int32_t, 3>> triangles;  // counter-clockwise seen from outside
  std::vector<uint8_t> parts;                     // per triangle (0 skin, 1 eye); empty: all 0

  // Area-weighted vertex normals (unit).
  std::vector<Eigen::Vector3f> VertexNormals() const;
};

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

class MeshSubject final : public Subject {
 public:
  // Builds the hierarchy (median splits, 4 triangles a leaf). `surface` null: the default Material, no detail.
  MeshSubject(TriangleMesh mesh, SurfaceFunction surface);
  Hit Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const override;
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const override;
  const TriangleMesh& mesh() const { return mesh_; }

 private:
  struct Node {
    Eigen::Vector3f lo = Eigen::Vector3f::Zero(), hi = Eigen::Vector3f::Zero();
    int32_t first = 0;  // leaf: first index into order_; inner: right child (left is this + 1)
    int32_t count = 0;  // leaf: triangles; inner: 0
  };
  int32_t Build(int32_t first, int32_t count);
  // The nearest triangle along the ray within (tmin, tmax): index, t, barycentrics; any hit only when `any`.
  bool Trace(const Eigen::Vector3f& o, const Eigen::Vector3f& d, float tmax, bool any, int32_t* tri, float* t,
             float* b1, float* b2) const;

  TriangleMesh mesh_;
  SurfaceFunction surface_;
  std::vector<Eigen::Vector3f> normals_;
  std::vector<Eigen::Vector3f> centroids_;  // build only
  std::vector<int32_t> order_;
  std::vector<Node> nodes_;
};

// Reads a Wavefront OBJ (v, vt, f; polygons fan-triangulated, negative indices allowed). Errors name the file and line.
absl::StatusOr<TriangleMesh> ReadObj(const std::string& path);
// Writes positions, texture coordinates and triangles as an OBJ (`comment` on its first line).
absl::Status WriteObj(const std::string& path, const TriangleMesh& mesh, const std::string& comment = "");

}  // namespace stage::sim
