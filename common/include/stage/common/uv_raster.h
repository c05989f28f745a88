// Rasterizing a mesh's UV layout: which triangle covers each texel of a square map, for the stage's UV maps (the
// simulator's truth, processing's geometry maps and textures).
//
// Texel (x, y) of a size x size map is centred at u = (x + 0.5) / size, v = 1 - (y + 0.5) / size: row 0 lies at v = 1,
// as images are stored and as other tools (Blender, MeshLab) read an OBJ's texture coordinates against an image.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "stage/common/mesh.h"

namespace stage {

struct UvTexel {
  int32_t triangle = -1;  // -1: no triangle covers the texel's centre
  float b1 = 0, b2 = 0;   // barycentrics of the triangle's vertices 1 and 2 at the centre
  bool covered() const { return triangle >= 0; }
};

// The centre of texel (x, y) of a size x size map in UV.
inline Eigen::Vector2f TexelUv(int x, int y, int size) {
  return {(static_cast<float>(x) + 0.5f) / static_cast<float>(size),
          1.0f - (static_cast<float>(y) + 0.5f) / static_cast<float>(size)};
}

// Per texel (row-major, size x size), the triangle of `mesh` covering its centre, among the triangles of part `part`
// (every part when `part` < 0). Where triangles overlap in UV the later one wins. Needs a uv per vertex.
std::vector<UvTexel> RasterizeUv(const TriangleMesh& mesh, int size, int part = 0);

// `values` (one per vertex) interpolated at every covered texel; `empty` where none covers it.
std::vector<Eigen::Vector3f> InterpolateAtTexels(const TriangleMesh& mesh, const std::vector<UvTexel>& texels,
                                                 const std::vector<Eigen::Vector3f>& values,
                                                 const Eigen::Vector3f& empty);

}  // namespace stage
