// Triangle meshes of the stage (the simulated subject, ground truth, reconstructed geometry): vertices, texture
// coordinates and parts, Wavefront OBJ files, and a bounding volume hierarchy for rays and shadow rays.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <iosfwd>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace stage {

struct TriangleMesh {
  std::vector<Eigen::Vector3f> positions;
  std::vector<Eigen::Vector2f> uvs;               // per vertex
  std::vector<std::array<int32_t, 3>> triangles;  // counter-clockwise seen from outside
  std::vector<uint8_t> parts;                     // per triangle (0 skin, 1 eye); empty: all 0
  // From an OBJ: per triangle the index of its material (`usemtl`) in `material_names`, -1 before any; and the
  // material libraries it names (`mtllib`, as written). Empty where the mesh has no materials.
  std::vector<int32_t> materials;
  std::vector<std::string> material_names;
  std::vector<std::string> material_libraries;

  // Area-weighted vertex normals (unit).
  std::vector<Eigen::Vector3f> VertexNormals() const;
};

// The same for `positions` over `triangles` (a mesh's topology with other positions, without copying the mesh).
std::vector<Eigen::Vector3f> VertexNormals(const std::vector<Eigen::Vector3f>& positions,
                                           const std::vector<std::array<int32_t, 3>>& triangles);

// Reads a Wavefront OBJ (v, vt, f; polygons fan-triangulated, negative indices allowed; usemtl and mtllib recorded;
// a file whose only materials are WriteObj's part names, with no library, gets its parts back). Errors name the file
// and line.
absl::StatusOr<TriangleMesh> ReadObj(const std::string& path);
// The same from a stream (an OBJ compiled into a program); `name` stands for the file in errors.
absl::StatusOr<TriangleMesh> ParseObj(std::istream& in, const std::string& name);
// Writes positions, texture coordinates (when every vertex has one) and triangles as an OBJ (`comment` on its first
// line), atomically (a temporary file renamed over `path`). Parts, where a mesh without materials has any besides
// 0, are written as materials without a library: `usemtl skin` (0) and `usemtl eye` (1).
absl::Status WriteObj(const std::string& path, const TriangleMesh& mesh, const std::string& comment = "");

// Where a ray meets a mesh: the triangle, the distance along the (unit) direction, and the barycentrics of vertices
// 1 and 2.
struct MeshHit {
  int32_t triangle = -1;
  float t = 0;
  float b1 = 0, b2 = 0;
};

// Rays through a mesh it owns: Embree's bounding volume hierarchy (docs/dependencies.md), built once. Const methods
// are thread-safe; copies share the mesh and the hierarchy.
class MeshBvh {
 public:
  explicit MeshBvh(TriangleMesh mesh);
  const TriangleMesh& mesh() const;
  // The nearest triangle along the ray (unit `direction`) within (1e-4, tmax); false if none.
  bool Nearest(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, float tmax, MeshHit* hit) const;
  // Whether anything lies on the segment from `from` to `to` (more than 1e-4 from `from`).
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const;
  // The same for many segments at once (`blocked[i]` for from[i] -> to[i]; the three spans of one size): Embree traces
  // them as a stream, in packets where consecutive segments run alike (neighbouring points towards one light), twice as
  // fast as one at a time for such segments (docs/simulator.md#cost). The answers are Occluded's.
  void Occluded(std::span<const Eigen::Vector3f> from, std::span<const Eigen::Vector3f> to,
                std::span<uint8_t> blocked) const;

 private:
  struct Scene;
  std::shared_ptr<const Scene> scene_;
};

}  // namespace stage
