// Closing a mesh's small holes (mvs_internal.h): every loop of boundary edges (an edge of one triangle) no longer
// than the limit is filled with rings of new vertices shrinking to its centre, and the new vertices are then faired
// (each moved to the mean of its neighbours, the loop held still) into the membrane the loop spans.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <unordered_map>

#include "mvs_internal.h"

namespace stage::processing {
namespace {

uint64_t EdgeKey(int32_t a, int32_t b) {
  return (static_cast<uint64_t>(static_cast<uint32_t>(std::min(a, b))) << 32) | static_cast<uint32_t>(std::max(a, b));
}

// The boundary's loops, each in the direction its triangles run along it (so a filling triangle runs against it).
// Where the boundary passes a vertex more than once (holes touching at a corner, as marching cubes leaves them), the
// walk along it is cut into simple loops there.
std::vector<std::vector<int32_t>> BoundaryLoops(const TriangleMesh& mesh) {
  std::unordered_map<uint64_t, int> uses;
  uses.reserve(mesh.triangles.size() * 2);
  for (const auto& t : mesh.triangles) {
    for (int k = 0; k < 3; ++k) ++uses[EdgeKey(t[k], t[(k + 1) % 3])];
  }
  // Each boundary edge a -> b as its triangle runs, by a, sorted (the result must not depend on hash order).
  std::vector<std::pair<int32_t, int32_t>> edges;
  for (const auto& t : mesh.triangles) {
    for (int k = 0; k < 3; ++k) {
      if (uses[EdgeKey(t[k], t[(k + 1) % 3])] == 1) edges.emplace_back(t[k], t[(k + 1) % 3]);
    }
  }
  std::sort(edges.begin(), edges.end());
  std::vector<char> used(edges.size(), 0);
  auto unused_from = [&](int32_t v) -> int64_t {
    auto it = std::lower_bound(edges.begin(), edges.end(), std::make_pair(v, INT32_MIN));
    for (; it != edges.end() && it->first == v; ++it) {
      if (!used[it - edges.begin()]) return it - edges.begin();
    }
    return -1;
  };
  std::vector<std::vector<int32_t>> loops;
  for (size_t s = 0; s < edges.size(); ++s) {
    if (used[s]) continue;
    std::vector<int32_t> path = {edges[s].first};
    std::unordered_map<int32_t, size_t> at = {{edges[s].first, 0}};
    int32_t v = edges[s].first;
    for (int64_t e = unused_from(v); e >= 0; e = unused_from(v)) {
      used[e] = 1;
      const int32_t w = edges[e].second;
      auto found = at.find(w);
      if (found == at.end()) {
        at[w] = path.size();
        path.push_back(w);
      } else {
        // Back at a vertex of the walk: what lies between is a simple loop.
        const size_t i = found->second;
        if (path.size() - i >= 3) loops.emplace_back(path.begin() + static_cast<std::ptrdiff_t>(i), path.end());
        for (size_t k = i + 1; k < path.size(); ++k) at.erase(path[k]);
        path.resize(i + 1);
      }
      v = w;
    }
  }
  return loops;
}

// A loop's size: twice the largest distance of its vertices from their centre (a ragged boundary's length says
// little of the hole's size).
double Diameter(const TriangleMesh& mesh, const std::vector<int32_t>& loop) {
  Eigen::Vector3f centre = Eigen::Vector3f::Zero();
  for (int32_t v : loop) centre += mesh.positions[v];
  centre /= static_cast<float>(loop.size());
  float radius = 0;
  for (int32_t v : loop) radius = std::max(radius, (mesh.positions[v] - centre).norm());
  return 2 * radius;
}

// Fills one loop: rings of its vertices' copies moved towards its centre, a fan about the centre; then the new
// vertices faired. Returns the filled area, mm^2.
double FillLoop(const std::vector<int32_t>& loop, TriangleMesh* mesh) {
  const int n = static_cast<int>(loop.size());
  Eigen::Vector3f centre = Eigen::Vector3f::Zero();
  for (int32_t v : loop) centre += mesh->positions[v];
  centre /= static_cast<float>(n);
  // Rings about a mean edge apart from the loop to the centre (the hole's radius is about n edges over 2 pi).
  const int rings = std::max(0, static_cast<int>(std::lround(n / (2 * M_PI))) - 1);
  const int32_t first_new = static_cast<int32_t>(mesh->positions.size());
  std::vector<int32_t> outer = loop;
  for (int r = 1; r <= rings; ++r) {
    const float f = static_cast<float>(r) / static_cast<float>(rings + 1);
    std::vector<int32_t> inner(n);
    for (int i = 0; i < n; ++i) {
      inner[i] = static_cast<int32_t>(mesh->positions.size());
      mesh->positions.push_back((1 - f) * mesh->positions[loop[i]] + f * centre);
    }
    // The loop runs a -> b in its triangles; the new ones run b -> a.
    for (int i = 0; i < n; ++i) {
      const int j = (i + 1) % n;
      mesh->triangles.push_back({outer[j], outer[i], inner[i]});
      mesh->triangles.push_back({outer[j], inner[i], inner[j]});
    }
    outer = std::move(inner);
  }
  const int32_t c = static_cast<int32_t>(mesh->positions.size());
  mesh->positions.push_back(centre);
  for (int i = 0; i < n; ++i) mesh->triangles.push_back({outer[(i + 1) % n], outer[i], c});

  // Fairing: the new vertices to the mean of their neighbours, the loop fixed, until it settles (a membrane).
  const int32_t count = static_cast<int32_t>(mesh->positions.size()) - first_new;
  std::vector<std::vector<int32_t>> ring(count);
  const size_t first_tri = mesh->triangles.size() - static_cast<size_t>(n) * (2 * rings + 1);
  for (size_t t = first_tri; t < mesh->triangles.size(); ++t) {
    const auto& tri = mesh->triangles[t];
    for (int k = 0; k < 3; ++k) {
      if (tri[k] < first_new) continue;
      ring[tri[k] - first_new].push_back(tri[(k + 1) % 3]);
      ring[tri[k] - first_new].push_back(tri[(k + 2) % 3]);
    }
  }
  for (auto& r : ring) {
    std::sort(r.begin(), r.end());
    r.erase(std::unique(r.begin(), r.end()), r.end());
  }
  for (int iteration = 0; iteration < 20 * (rings + 1); ++iteration) {
    for (int32_t v = 0; v < count; ++v) {
      Eigen::Vector3f mean = Eigen::Vector3f::Zero();
      for (int32_t u : ring[v]) mean += mesh->positions[u];
      mesh->positions[first_new + v] = mean / static_cast<float>(ring[v].size());
    }
  }
  double area = 0;
  for (size_t t = first_tri; t < mesh->triangles.size(); ++t) {
    const auto& tri = mesh->triangles[t];
    const auto& p = mesh->positions;
    area += 0.5 * (p[tri[1]] - p[tri[0]]).cross(p[tri[2]] - p[tri[0]]).norm();
  }
  return area;
}

}  // namespace

HoleFill FillHoles(double max_diameter_mm, TriangleMesh* mesh) {
  HoleFill out;
  if (max_diameter_mm <= 0) return out;
  for (const std::vector<int32_t>& loop : BoundaryLoops(*mesh)) {
    if (Diameter(*mesh, loop) > max_diameter_mm) continue;
    out.area_mm2 += FillLoop(loop, mesh);
    ++out.holes;
  }
  return out;
}

}  // namespace stage::processing
