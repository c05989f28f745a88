// Closing a mesh's small holes (mvs_internal.h): every loop of boundary edges (an edge of one triangle) is spanned by
// the triangles between its vertices of least area, and kept where the hole is narrow enough: 4 x that area over
// the loop's length (a disc's diameter, a crack's width) within the limit.
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <unordered_map>

#include "mvs_internal.h"

namespace stage::processing {
namespace {

// A hole is filled if at most this many boundary vertices long, and at most kMaxLength times as long as wide.
constexpr size_t kMaxLoop = 600;
constexpr double kMaxLength = 5;

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

double Perimeter(const TriangleMesh& mesh, const std::vector<int32_t>& loop) {
  double sum = 0;
  for (size_t i = 0; i < loop.size(); ++i) {
    sum += (mesh.positions[loop[(i + 1) % loop.size()]] - mesh.positions[loop[i]]).norm();
  }
  return sum;
}

// A loop's length: twice the largest distance of its vertices from their centre (a ragged boundary's length says
// little of the hole's size).
double Diameter(const TriangleMesh& mesh, const std::vector<int32_t>& loop) {
  Eigen::Vector3f centre = Eigen::Vector3f::Zero();
  for (int32_t v : loop) centre += mesh.positions[v];
  centre /= static_cast<float>(loop.size());
  float radius = 0;
  for (int32_t v : loop) radius = std::max(radius, (mesh.positions[v] - centre).norm());
  return 2 * radius;
}

double TriangleArea(const Eigen::Vector3f& a, const Eigen::Vector3f& b, const Eigen::Vector3f& c) {
  return 0.5 * (b - a).cross(c - a).norm();
}

// The triangulation of a loop of least area (Liepa 2003's dynamic programme, O(n^3)): a hole's boundary spanned by
// triangles between its own vertices, whatever its shape (a crack as well as a disc). Triangles run against the
// loop's direction. Returns the area.
double SpanLoop(const TriangleMesh& mesh, const std::vector<int32_t>& loop,
                std::vector<std::array<int32_t, 3>>* triangles) {
  const int n = static_cast<int>(loop.size());
  auto at = [&](int i) -> const Eigen::Vector3f& { return mesh.positions[loop[i]]; };
  // area[i][k]: the least area spanning loop[i..k] and the chord k -> i; split[i][k]: its apex.
  std::vector<double> area(static_cast<size_t>(n) * n, 0);
  std::vector<int> split(static_cast<size_t>(n) * n, -1);
  auto idx = [n](int i, int k) { return static_cast<size_t>(i) * n + k; };
  for (int len = 2; len < n; ++len) {
    for (int i = 0; i + len < n; ++i) {
      const int k = i + len;
      double best = INFINITY;
      for (int m = i + 1; m < k; ++m) {
        const double a = area[idx(i, m)] + area[idx(m, k)] + TriangleArea(at(i), at(m), at(k));
        if (a < best) best = a, split[idx(i, k)] = m;
      }
      area[idx(i, k)] = best;
    }
  }
  std::vector<std::pair<int, int>> todo = {{0, n - 1}};
  while (!todo.empty()) {
    const auto [i, k] = todo.back();
    todo.pop_back();
    if (k - i < 2) continue;
    const int m = split[idx(i, k)];
    triangles->push_back({loop[k], loop[m], loop[i]});
    todo.emplace_back(i, m);
    todo.emplace_back(m, k);
  }
  return area[idx(0, n - 1)];
}

}  // namespace

HoleFill FillHoles(double max_width_mm, TriangleMesh* mesh) {
  HoleFill out;
  if (max_width_mm <= 0) return out;
  for (const std::vector<int32_t>& loop : BoundaryLoops(*mesh)) {
    // Long openings (the mesh's own border, the mouth) are left; the programme is cubic in the loop's length.
    if (loop.size() > kMaxLoop || Diameter(*mesh, loop) > kMaxLength * max_width_mm) continue;
    std::vector<std::array<int32_t, 3>> patch;
    const double area = SpanLoop(*mesh, loop, &patch);
    if (4 * area / Perimeter(*mesh, loop) > max_width_mm) continue;
    mesh->triangles.insert(mesh->triangles.end(), patch.begin(), patch.end());
    out.area_mm2 += area;
    ++out.holes;
  }
  return out;
}

}  // namespace stage::processing
