// Triangle meshes and OBJ files (mesh_bvh.cc: rays through them).
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
