// Triangle meshes, OBJ files and the bounding volume hierarchy.
#include "stage/common/mesh.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"

namespace stage {
namespace {

// The names WriteObj gives parts 0 and 1, as materials.
constexpr const char* kPartNames[2] = {"skin", "eye"};

}  // namespace

std::vector<Eigen::Vector3f> TriangleMesh::VertexNormals() const { return stage::VertexNormals(positions, triangles); }

std::vector<Eigen::Vector3f> VertexNormals(const std::vector<Eigen::Vector3f>& positions,
                                           const std::vector<std::array<int32_t, 3>>& triangles) {
  // Vertices at the same place (a texture seam, a pole) share one normal.
  std::map<std::array<float, 3>, int32_t> first;
  std::vector<int32_t> welded(positions.size());
  for (size_t v = 0; v < positions.size(); ++v) {
    welded[v] = first.try_emplace({positions[v].x(), positions[v].y(), positions[v].z()}, static_cast<int32_t>(v))
                    .first->second;
  }
  std::vector<Eigen::Vector3f> n(positions.size(), Eigen::Vector3f::Zero());
  for (const auto& t : triangles) {
    const Eigen::Vector3f a = positions[t[0]], b = positions[t[1]], c = positions[t[2]];
    const Eigen::Vector3f area = (b - a).cross(c - a);  // twice the area, along the normal
    for (int k = 0; k < 3; ++k) n[welded[t[k]]] += area;
  }
  for (size_t v = 0; v < n.size(); ++v) n[v] = n[welded[v]];
  for (auto& v : n) {
    const float len = v.norm();
    v = len > 0 ? Eigen::Vector3f(v / len) : Eigen::Vector3f(Eigen::Vector3f::UnitZ());
  }
  return n;
}

MeshBvh::MeshBvh(TriangleMesh mesh) : mesh_(std::move(mesh)) {
  const auto n = static_cast<int32_t>(mesh_.triangles.size());
  order_.resize(static_cast<size_t>(n));
  std::vector<Eigen::Vector3f> centroids(static_cast<size_t>(n));
  for (int32_t i = 0; i < n; ++i) {
    order_[i] = i;
    const auto& t = mesh_.triangles[i];
    centroids[i] = (mesh_.positions[t[0]] + mesh_.positions[t[1]] + mesh_.positions[t[2]]) / 3;
  }
  nodes_.reserve(static_cast<size_t>(2 * n / 4 + 2));
  if (n > 0) Build(0, n, centroids);
}

int32_t MeshBvh::Build(int32_t first, int32_t count, const std::vector<Eigen::Vector3f>& centroids) {
  const auto index = static_cast<int32_t>(nodes_.size());
  nodes_.push_back({});
  Eigen::Vector3f lo = Eigen::Vector3f::Constant(INFINITY), hi = Eigen::Vector3f::Constant(-INFINITY);
  Eigen::Vector3f clo = lo, chi = hi;
  for (int32_t i = first; i < first + count; ++i) {
    for (int32_t v : mesh_.triangles[order_[i]]) {
      lo = lo.cwiseMin(mesh_.positions[v]);
      hi = hi.cwiseMax(mesh_.positions[v]);
    }
    clo = clo.cwiseMin(centroids[order_[i]]);
    chi = chi.cwiseMax(centroids[order_[i]]);
  }
  nodes_[index].lo = lo;
  nodes_[index].hi = hi;
  if (count <= 4) {
    nodes_[index].first = first;
    nodes_[index].count = count;
    return index;
  }
  int axis = 0;
  (chi - clo).maxCoeff(&axis);
  const int32_t mid = first + count / 2;
  std::nth_element(order_.begin() + first, order_.begin() + mid, order_.begin() + first + count,
                   [&](int32_t a, int32_t b) { return centroids[a][axis] < centroids[b][axis]; });
  Build(first, mid - first, centroids);
  const int32_t right = Build(mid, first + count - mid, centroids);
  nodes_[index].first = right;
  nodes_[index].count = 0;
  return index;
}

namespace {

// Slab test: does the ray enter the box before `tmax`?
inline bool HitsBox(const Eigen::Vector3f& lo, const Eigen::Vector3f& hi, const Eigen::Vector3f& o,
                    const Eigen::Vector3f& inv, float tmax) {
  float t0 = 0, t1 = tmax;
  for (int a = 0; a < 3; ++a) {
    float near = (lo[a] - o[a]) * inv[a], far = (hi[a] - o[a]) * inv[a];
    if (near > far) std::swap(near, far);
    t0 = std::max(t0, near);
    t1 = std::min(t1, far);
    if (t0 > t1) return false;
  }
  return true;
}

}  // namespace

bool MeshBvh::Trace(const Eigen::Vector3f& o, const Eigen::Vector3f& d, float tmax, bool any, MeshHit* hit) const {
  if (nodes_.empty()) return false;
  const Eigen::Vector3f inv(1 / d.x(), 1 / d.y(), 1 / d.z());
  int32_t stack[64];
  int top = 0;
  stack[top++] = 0;
  bool found = false;
  float best = tmax;
  while (top > 0) {
    const Node& node = nodes_[stack[--top]];
    if (!HitsBox(node.lo, node.hi, o, inv, best)) continue;
    if (node.count == 0) {
      const int32_t self = static_cast<int32_t>(&node - nodes_.data());
      stack[top++] = node.first;
      stack[top++] = self + 1;
      continue;
    }
    for (int32_t i = node.first; i < node.first + node.count; ++i) {
      const auto& tr = mesh_.triangles[order_[i]];
      // Moeller-Trumbore.
      const Eigen::Vector3f& a = mesh_.positions[tr[0]];
      const Eigen::Vector3f e1 = mesh_.positions[tr[1]] - a, e2 = mesh_.positions[tr[2]] - a;
      const Eigen::Vector3f p = d.cross(e2);
      const float det = e1.dot(p);
      // Parallel or degenerate (relative to the triangle's size: float rounding leaves such dets far from 0).
      if (std::abs(det) <= 1e-6f * e1.norm() * e2.norm()) continue;
      const float inv_det = 1 / det;
      const Eigen::Vector3f s = o - a;
      const float u = s.dot(p) * inv_det;
      if (u < 0 || u > 1) continue;
      const Eigen::Vector3f q = s.cross(e1);
      const float v = d.dot(q) * inv_det;
      if (v < 0 || u + v > 1) continue;
      const float t = e2.dot(q) * inv_det;
      if (t <= 1e-4f || t >= best) continue;
      best = t;
      found = true;
      if (any) return true;
      hit->triangle = order_[i];
      hit->t = t;
      hit->b1 = u;
      hit->b2 = v;
    }
  }
  return found;
}

bool MeshBvh::Nearest(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, float tmax, MeshHit* hit) const {
  return Trace(origin, direction, tmax, false, hit);
}

bool MeshBvh::Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const {
  const Eigen::Vector3f d = to - from;
  const float len = d.norm();
  MeshHit hit;
  return Trace(from, d / len, len, true, &hit);
}

absl::StatusOr<TriangleMesh> ReadObj(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open the OBJ file"));
  return ParseObj(in, path);
}

absl::StatusOr<TriangleMesh> ParseObj(std::istream& in, const std::string& path) {
  std::vector<Eigen::Vector3f> v;
  std::vector<Eigen::Vector2f> vt;
  TriangleMesh mesh;
  std::map<std::pair<int, int>, int32_t> vertex_of;  // (v, vt) -> mesh vertex
  std::string line;
  int line_no = 0;
  int32_t material = -1;  // the current usemtl's index
  auto bad = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat(path, ":", line_no, ": ", what));
  };
  while (std::getline(in, line)) {
    ++line_no;
    std::vector<std::string> f = absl::StrSplit(line, absl::ByAnyChar(" \t\r"), absl::SkipEmpty());
    if (f.empty() || f[0][0] == '#') continue;
    auto num = [&](size_t i, float* out) { return i < f.size() && absl::SimpleAtof(f[i], out); };
    if (f[0] == "v") {
      Eigen::Vector3f p;
      if (!num(1, &p.x()) || !num(2, &p.y()) || !num(3, &p.z())) return bad("a vertex needs three numbers");
      v.push_back(p);
    } else if (f[0] == "vt") {
      Eigen::Vector2f t;
      if (!num(1, &t.x()) || !num(2, &t.y())) return bad("a texture coordinate needs two numbers");
      vt.push_back(t);
    } else if (f[0] == "usemtl" && f.size() > 1) {
      auto found = std::find(mesh.material_names.begin(), mesh.material_names.end(), f[1]);
      material = static_cast<int32_t>(found - mesh.material_names.begin());
      if (found == mesh.material_names.end()) mesh.material_names.push_back(f[1]);
    } else if (f[0] == "mtllib" && f.size() > 1) {
      mesh.material_libraries.push_back(f[1]);
    } else if (f[0] == "f") {
      if (f.size() < 4) return bad("a face needs at least three vertices");
      std::vector<int32_t> corners;
      for (size_t i = 1; i < f.size(); ++i) {
        std::vector<std::string> idx = absl::StrSplit(f[i], '/');
        int vi = 0, ti = 0;
        if (!absl::SimpleAtoi(idx[0], &vi) || vi == 0) return bad(absl::StrCat("bad vertex index \"", f[i], "\""));
        if (idx.size() > 1 && !idx[1].empty() && !absl::SimpleAtoi(idx[1], &ti)) {
          return bad(absl::StrCat("bad texture index \"", f[i], "\""));
        }
        vi = vi < 0 ? static_cast<int>(v.size()) + vi : vi - 1;
        if (ti != 0)
          ti = ti < 0 ? static_cast<int>(vt.size()) + ti : ti - 1;
        else
          ti = -1;
        if (vi < 0 || vi >= static_cast<int>(v.size())) return bad(absl::StrCat("vertex ", f[i], " is not defined"));
        if (ti >= static_cast<int>(vt.size())) return bad(absl::StrCat("texture coordinate ", f[i], " is not defined"));
        auto [it, inserted] = vertex_of.try_emplace({vi, ti}, static_cast<int32_t>(mesh.positions.size()));
        if (inserted) {
          mesh.positions.push_back(v[vi]);
          mesh.uvs.push_back(ti >= 0 ? vt[ti] : Eigen::Vector2f::Zero());
        }
        corners.push_back(it->second);
      }
      for (size_t i = 1; i + 1 < corners.size(); ++i) {
        mesh.triangles.push_back({corners[0], corners[i], corners[i + 1]});
        mesh.materials.push_back(material);
      }
    }
  }
  if (mesh.triangles.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no faces"));
  if (mesh.material_names.empty()) mesh.materials.clear();
  // WriteObj's parts (usemtl skin / eye, no material library) come back as parts.
  const bool parts = mesh.material_libraries.empty() && !mesh.material_names.empty() &&
                     std::all_of(mesh.material_names.begin(), mesh.material_names.end(),
                                 [](const std::string& n) { return n == kPartNames[0] || n == kPartNames[1]; });
  if (parts) {
    for (int32_t m : mesh.materials) mesh.parts.push_back(m >= 0 && mesh.material_names[m] == kPartNames[1] ? 1 : 0);
  }
  return mesh;
}

absl::Status WriteObj(const std::string& path, const TriangleMesh& mesh, const std::string& comment) {
  // Written beside and renamed over `path`: a reader never sees half a mesh.
  const std::string temporary = path + ".partial";
  std::ofstream out(temporary);
  if (!out) return absl::UnavailableError(absl::StrCat(path, ": cannot write"));
  if (!comment.empty()) out << "# " << comment << "\n";
  for (const auto& p : mesh.positions) out << absl::StrFormat("v %.4f %.4f %.4f\n", p.x(), p.y(), p.z());
  const bool uvs = !mesh.uvs.empty() && mesh.uvs.size() == mesh.positions.size();
  if (uvs) {
    for (const auto& t : mesh.uvs) out << absl::StrFormat("vt %.6f %.6f\n", t.x(), t.y());
  }
  // Parts as materials (usemtl skin / eye), where the mesh has parts and no materials of its own.
  const bool parts = mesh.materials.empty() && mesh.parts.size() == mesh.triangles.size() &&
                     std::any_of(mesh.parts.begin(), mesh.parts.end(), [](uint8_t p) { return p != 0; });
  int part = -1;
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    const auto& f = mesh.triangles[t];
    if (parts && std::min<int>(mesh.parts[t], 1) != part) {
      part = std::min<int>(mesh.parts[t], 1);
      out << "usemtl " << kPartNames[part] << "\n";
    }
    if (uvs) {
      out << absl::StrFormat("f %d/%d %d/%d %d/%d\n", f[0] + 1, f[0] + 1, f[1] + 1, f[1] + 1, f[2] + 1, f[2] + 1);
    } else {
      out << absl::StrFormat("f %d %d %d\n", f[0] + 1, f[1] + 1, f[2] + 1);
    }
  }
  out.close();
  if (!out) return absl::DataLossError(absl::StrCat(path, ": write failed"));
  std::error_code ec;
  std::filesystem::rename(temporary, path, ec);
  if (ec) return absl::DataLossError(absl::StrCat(path, ": cannot rename the written file over it: ", ec.message()));
  return absl::OkStatus();
}

}  // namespace stage
