#include "stage/common/uv_raster.h"

#include <algorithm>
#include <cmath>

namespace stage {

std::vector<UvTexel> RasterizeUv(const TriangleMesh& mesh, int size, int part) {
  std::vector<UvTexel> texels(static_cast<size_t>(size) * size);
  if (mesh.uvs.size() != mesh.positions.size()) return texels;
  const float s = static_cast<float>(size);
  for (size_t k = 0; k < mesh.triangles.size(); ++k) {
    if (part >= 0 && (mesh.parts.empty() ? 0 : mesh.parts[k]) != part) continue;
    const auto& t = mesh.triangles[k];
    // In texel units, rows downwards: (u s, (1 - v) s).
    auto at = [&](int32_t i) { return Eigen::Vector2f(mesh.uvs[i].x() * s, (1.0f - mesh.uvs[i].y()) * s); };
    const Eigen::Vector2f a = at(t[0]), b = at(t[1]), c = at(t[2]);
    const float det = (b.x() - a.x()) * (c.y() - a.y()) - (c.x() - a.x()) * (b.y() - a.y());
    if (std::abs(det) < 1e-12f) continue;
    const int x0 = std::max(0, static_cast<int>(std::floor(std::min({a.x(), b.x(), c.x()}))));
    const int x1 = std::min(size - 1, static_cast<int>(std::ceil(std::max({a.x(), b.x(), c.x()}))));
    const int y0 = std::max(0, static_cast<int>(std::floor(std::min({a.y(), b.y(), c.y()}))));
    const int y1 = std::min(size - 1, static_cast<int>(std::ceil(std::max({a.y(), b.y(), c.y()}))));
    for (int y = y0; y <= y1; ++y) {
      for (int x = x0; x <= x1; ++x) {
        const float px = static_cast<float>(x) + 0.5f, py = static_cast<float>(y) + 0.5f;
        const float w1 = ((px - a.x()) * (c.y() - a.y()) - (c.x() - a.x()) * (py - a.y())) / det;
        const float w2 = ((b.x() - a.x()) * (py - a.y()) - (px - a.x()) * (b.y() - a.y())) / det;
        if (w1 < -1e-6f || w2 < -1e-6f || 1 - w1 - w2 < -1e-6f) continue;
        texels[static_cast<size_t>(y) * size + x] = {static_cast<int32_t>(k), w1, w2};
      }
    }
  }
  return texels;
}

std::vector<Eigen::Vector3f> InterpolateAtTexels(const TriangleMesh& mesh, const std::vector<UvTexel>& texels,
                                                 const std::vector<Eigen::Vector3f>& values,
                                                 const Eigen::Vector3f& empty) {
  std::vector<Eigen::Vector3f> out(texels.size(), empty);
  for (size_t i = 0; i < texels.size(); ++i) {
    const UvTexel& texel = texels[i];
    if (!texel.covered()) continue;
    const auto& t = mesh.triangles[static_cast<size_t>(texel.triangle)];
    out[i] = (1 - texel.b1 - texel.b2) * values[t[0]] + texel.b1 * values[t[1]] + texel.b2 * values[t[2]];
  }
  return out;
}

}  // namespace stage
