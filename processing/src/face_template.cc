#include "stage/processing/face_template.h"

#include <bit>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "stage/common/file_util.h"

extern const char kFaceTemplateObj[];
extern const char kFaceTemplateJson[];
extern const unsigned char kFaceModelF32[];
extern const unsigned char kFaceModelF32_end[];

namespace stage::processing {
namespace {

// The bytes of a model file (`dir`/`file`), or of the shipped one when `dir` is empty.
absl::StatusOr<std::string> ModelBytes(const std::string& dir, const std::string& file) {
  if (dir.empty()) {
    return std::string(reinterpret_cast<const char*>(kFaceModelF32),
                       static_cast<size_t>(kFaceModelF32_end - kFaceModelF32));
  }
  return ReadFileToString(dir + "/" + file, "the template's model");
}

// The JSON's "model" read into `t` from the model file in `dir` (empty: the shipped one).
absl::Status ReadModel(const nlohmann::json& m, const std::string& dir, const std::string& name, FaceTemplate* t) {
  static_assert(std::endian::native == std::endian::little, "face-model.f32 is little-endian");
  auto bad = [&](const std::string& field, const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": model.", field, ": ", what));
  };
  size_t vertices = 0, components = 0;
  std::string file;
  try {
    file = m.at("file").get<std::string>();
    vertices = m.at("vertices").get<size_t>();
    components = m.at("identity_components").get<size_t>();
    t->expression_names = m.at("expressions").get<std::vector<std::string>>();
  } catch (const nlohmann::json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": model: ", e.what()));
  }
  if (vertices != t->mesh.positions.size() || vertices == 0) {
    return bad("vertices", absl::StrCat(vertices, ", the mesh has ", t->mesh.positions.size()));
  }
  if (file.empty() || file.find('/') != std::string::npos || file == "." || file == "..") {
    return bad("file", absl::StrCat("\"", file, "\" is not a file name beside the description"));
  }
  auto bytes = ModelBytes(dir, file);
  if (!bytes.ok()) return bytes.status();
  static_assert(sizeof(Eigen::Vector3f) == 3 * sizeof(float), "a vertex's three floats are packed");
  const size_t per = vertices * 3 * sizeof(float), held = bytes->size() / per;
  const size_t count = components + t->expression_names.size();
  if (components > held || count > held || bytes->size() != count * per) {
    return bad("file", absl::StrCat(file, " holds ", bytes->size(), " bytes, not the ", count * per, " of ", count,
                                    " components of ", vertices, " vertices"));
  }
  for (size_t k = 0; k < count; ++k) {
    std::vector<Eigen::Vector3f> component(vertices);
    std::memcpy(static_cast<void*>(component.data()), bytes->data() + k * per, per);
    for (const Eigen::Vector3f& d : component) {
      if (!d.allFinite())
        return bad("file", absl::StrCat(file, ": component ", k, " holds a value that is not finite"));
    }
    (k < components ? t->identity_basis : t->expression_basis).push_back(std::move(component));
  }
  return absl::OkStatus();
}

// The template from its mesh and its JSON text; `name` stands for the JSON file in errors, `dir` is where the files
// beside it are (empty: the shipped template's, compiled in).
absl::StatusOr<FaceTemplate> FromParts(TriangleMesh mesh, const std::string& json_text, const std::string& name,
                                       const std::string& dir) {
  FaceTemplate t;
  t.mesh = std::move(mesh);
  if (t.mesh.uvs.size() != t.mesh.positions.size()) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": the template's mesh needs a texture coordinate a vertex"));
  }
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(json_text);
  } catch (const nlohmann::json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": ", e.what()));
  }
  auto bad = [&](const std::string& field, const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": ", field, ": ", what));
  };
  if (j.value("format", "") != "fastage-face-template") return bad("format", "is not \"fastage-face-template\"");
  if (j.value("version", 0) != 1) return bad("version", "only version 1 is read");
  t.source = j.value("source", "");
  try {
    const auto& w = j.at("head_layout_window");
    t.head_layout_lo = {w.at("u").at(0).get<float>(), w.at("v").at(0).get<float>()};
    t.head_layout_hi = {w.at("u").at(1).get<float>(), w.at("v").at(1).get<float>()};
  } catch (const nlohmann::json::exception& e) {
    return bad("head_layout_window", e.what());
  }
  t.regions.assign(t.mesh.positions.size(), FaceRegion::kSkin);
  for (const auto& [key, region] : {std::pair{"eyes", FaceRegion::kEye}, std::pair{"mouth", FaceRegion::kMouth}}) {
    if (!j.contains("regions") || !j["regions"].contains(key)) continue;
    for (const auto& v : j["regions"][key]) {
      if (!v.is_number_integer() || v.get<int64_t>() < 0 ||
          v.get<int64_t>() >= static_cast<int64_t>(t.regions.size())) {
        return bad(absl::StrCat("regions.", key), absl::StrCat(v.dump(), " is not a vertex of the mesh"));
      }
      t.regions[v.get<size_t>()] = region;
    }
  }
  t.jaw_weight.assign(t.mesh.positions.size(), 0.0f);
  if (j.contains("jaw")) {
    try {
      const auto& jaw = j.at("jaw");
      const auto& h = jaw.at("hinge_mm");
      const auto& a = jaw.at("axis");
      t.jaw_hinge = {h.at(0).get<float>(), h.at(1).get<float>(), h.at(2).get<float>()};
      t.jaw_axis = Eigen::Vector3f(a.at(0).get<float>(), a.at(1).get<float>(), a.at(2).get<float>()).normalized();
      const auto& vertices = jaw.at("vertices");
      const auto& weights = jaw.at("weights");
      if (vertices.size() != weights.size()) return bad("jaw", "vertices and weights differ in count");
      for (size_t k = 0; k < vertices.size(); ++k) {
        const int64_t v = vertices[k].get<int64_t>();
        const float w = weights[k].get<float>();
        if (v < 0 || v >= static_cast<int64_t>(t.jaw_weight.size())) {
          return bad("jaw.vertices", absl::StrCat(v, " is not a vertex of the mesh"));
        }
        if (!(w >= 0 && w <= 1)) return bad("jaw.weights", absl::StrCat(w, " is not in [0, 1]"));
        t.jaw_weight[static_cast<size_t>(v)] = w;
      }
    } catch (const nlohmann::json::exception& e) {
      return bad("jaw", e.what());
    }
  }
  if (j.contains("model")) {
    if (auto s = ReadModel(j.at("model"), dir, name, &t); !s.ok()) return s;
  }
  return t;
}

}  // namespace

absl::StatusOr<FaceTemplate> LoadFaceTemplate(const std::string& obj_path) {
  auto mesh = ReadObj(obj_path);
  if (!mesh.ok()) return mesh.status();
  std::string json_path = obj_path;
  if (json_path.size() > 4 && json_path.substr(json_path.size() - 4) == ".obj") json_path.resize(json_path.size() - 4);
  json_path += ".json";
  std::ifstream in(json_path);
  if (!in) return absl::NotFoundError(absl::StrCat(json_path, ": cannot open the template's description"));
  std::stringstream text;
  text << in.rdbuf();
  const std::string dir = std::filesystem::path(json_path).parent_path().string();
  return FromParts(*std::move(mesh), text.str(), json_path, dir.empty() ? "." : dir);
}

absl::StatusOr<FaceTemplate> ShippedFaceTemplate() {
  std::istringstream obj(kFaceTemplateObj);
  auto mesh = ParseObj(obj, "(shipped) face-template.obj");
  if (!mesh.ok()) return mesh.status();
  return FromParts(*std::move(mesh), kFaceTemplateJson, "(shipped) face-template.json", "");
}

}  // namespace stage::processing
