// Calibration files: see camera_calibration.h.
#include "stage/common/camera_calibration.h"

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "stage/common/file_util.h"

namespace stage {
namespace {

constexpr const char* kFormat = "fastage-camera-calibration";

// Reads `count` finite numbers of field `name`; errors name it.
absl::Status Numbers(const nlohmann::json& entry, const std::string& where, const char* name, size_t count,
                     double* out) {
  const auto it = entry.find(name);
  if (it == entry.end()) return absl::InvalidArgumentError(absl::StrCat(where, ".", name, ": missing"));
  const nlohmann::json& v = *it;
  if (count == 1 && v.is_number()) {
    out[0] = v.get<double>();
  } else if (v.is_array() && v.size() == count) {
    for (size_t i = 0; i < count; ++i) {
      if (!v[i].is_number()) return absl::InvalidArgumentError(absl::StrCat(where, ".", name, ": not a number"));
      out[i] = v[i].get<double>();
    }
  } else {
    return absl::InvalidArgumentError(absl::StrCat(where, ".", name, ": expected ", count, " number(s)"));
  }
  for (size_t i = 0; i < count; ++i) {
    if (!std::isfinite(out[i])) return absl::InvalidArgumentError(absl::StrCat(where, ".", name, ": not finite"));
  }
  return absl::OkStatus();
}

absl::StatusOr<CalibratedCamera> ParseCamera(const nlohmann::json& entry, const std::string& where) {
  if (!entry.is_object()) return absl::InvalidArgumentError(absl::StrCat(where, ": not an object"));
  CalibratedCamera c;
  if (!entry.contains("id") || !entry["id"].is_string() || entry["id"].get<std::string>().empty()) {
    return absl::InvalidArgumentError(absl::StrCat(where, ".id: missing"));
  }
  c.id = entry["id"].get<std::string>();
  CameraParameters p;
  double size[2], rotation[9];
  absl::Status s = Numbers(entry, where, "width", 1, &size[0]);
  if (s.ok()) s = Numbers(entry, where, "height", 1, &size[1]);
  if (s.ok()) s = Numbers(entry, where, "fx", 1, &p.fx);
  if (s.ok()) s = Numbers(entry, where, "fy", 1, &p.fy);
  if (s.ok()) s = Numbers(entry, where, "cx", 1, &p.cx);
  if (s.ok()) s = Numbers(entry, where, "cy", 1, &p.cy);
  if (s.ok()) s = Numbers(entry, where, "distortion", 5, p.distortion.data());
  if (s.ok()) s = Numbers(entry, where, "position_mm", 3, p.position.data());
  if (s.ok()) s = Numbers(entry, where, "rotation", 9, rotation);
  if (!s.ok()) return s;
  for (int k = 0; k < 2; ++k) {
    if (!(size[k] >= 1 && size[k] <= 1e6) || size[k] != std::floor(size[k])) {
      return absl::InvalidArgumentError(absl::StrCat(where, k == 0 ? ".width" : ".height", ": not a pixel count"));
    }
  }
  p.width = static_cast<int>(size[0]);
  p.height = static_cast<int>(size[1]);
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) p.rotation(r, k) = rotation[3 * r + k];
  }
  auto model = CameraModel::FromParameters(p);
  if (!model.ok()) return absl::InvalidArgumentError(absl::StrCat(where, " (\"", c.id, "\"): ", model.status().message()));
  c.model = *std::move(model);
  return c;
}

}  // namespace

const CameraModel* CameraCalibration::Find(const std::string& id) const {
  for (const CalibratedCamera& c : cameras) {
    if (c.id == id) return &c.model;
  }
  return nullptr;
}

absl::StatusOr<CameraCalibration> ReadCameraCalibration(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open the calibration file"));
  std::stringstream text;
  text << in.rdbuf();
  const nlohmann::json j = nlohmann::json::parse(text.str(), nullptr, /*allow_exceptions=*/false);
  auto bad = [&](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat(path, ": ", what)); };
  if (j.is_discarded()) return bad("not JSON");
  if (!j.is_object() || !j.contains("format") || !j["format"].is_string() || j["format"] != kFormat) {
    return bad(absl::StrCat("not a ", kFormat, " file"));
  }
  if (!j.contains("version") || !j["version"].is_number_integer() || j["version"] != 1) {
    return bad("version: only version 1 is read");
  }
  if (!j.contains("cameras") || !j["cameras"].is_array()) return bad("cameras: missing");
  if (j.contains("source") && !j["source"].is_string()) return bad("source: not a string");
  CameraCalibration out;
  out.source = j.value("source", "");
  for (size_t i = 0; i < j["cameras"].size(); ++i) {
    auto c = ParseCamera(j["cameras"][i], absl::StrCat("cameras[", i, "]"));
    if (!c.ok()) return bad(std::string(c.status().message()));
    if (out.Find(c->id) != nullptr) return bad(absl::StrCat("cameras[", i, "]: camera \"", c->id, "\" twice"));
    out.cameras.push_back(*std::move(c));
  }
  return out;
}

absl::Status WriteCameraCalibration(const std::string& path, const CameraCalibration& calibration) {
  nlohmann::json cameras = nlohmann::json::array();
  for (const CalibratedCamera& c : calibration.cameras) {
    const CameraParameters p = c.model.parameters();
    nlohmann::json rotation = nlohmann::json::array();
    for (int r = 0; r < 3; ++r) {
      for (int k = 0; k < 3; ++k) rotation.push_back(p.rotation(r, k));
    }
    cameras.push_back({{"id", c.id},
                       {"width", p.width},
                       {"height", p.height},
                       {"fx", p.fx},
                       {"fy", p.fy},
                       {"cx", p.cx},
                       {"cy", p.cy},
                       {"distortion", p.distortion},
                       {"position_mm", {p.position.x(), p.position.y(), p.position.z()}},
                       {"rotation", rotation}});
  }
  const nlohmann::json j = {
      {"format", kFormat}, {"version", 1}, {"source", calibration.source}, {"cameras", cameras}};
  return WriteFileAtomically(path, j.dump(2) + "\n");
}

}  // namespace stage
