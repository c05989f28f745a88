// The face template made from the shipped procedural head.
#include "stage/sim/face_template.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace stage::sim {
namespace {

constexpr float kPi = 3.14159265358979323846f;

// The template's window in the head's skin layout: azimuth +-79 degrees (the ears, at +-93, left out: a fit gains
// little there and multi-view stereo sees them edge on), elevation from 68 degrees below the head's centre (under the
// chin) to 50 above (the forehead).
constexpr float kULo = 0.28f, kUHi = 0.72f, kVLo = 0.12f, kVHi = 0.78f;

TemplateRegion RegionAt(const Eigen::Vector2f& head_uv, const HeadLandmarks& landmarks) {
  const float azimuth = (head_uv.x() - 0.5f) * 2 * kPi, elevation = (head_uv.y() - 0.5f) * kPi;
  // The eyes' openings: where the lids close over the eyeballs (the blink's reach).
  for (float side : {1.0f, -1.0f}) {
    const float a = (azimuth - side * landmarks.eye_azimuth) / 0.13f,
                e = (elevation - landmarks.eye_elevation) / 0.075f;
    if (a * a + e * e < 1) return TemplateRegion::kEye;
  }
  // The mouth's opening: the lips' inner edges about the mouth line, which the jaw opens.
  if (std::abs(azimuth) < 0.2f && std::abs(elevation - landmarks.mouth_elevation) < 0.03f) {
    return TemplateRegion::kMouth;
  }
  return TemplateRegion::kSkin;
}

// How far the skin at `head_uv` follows the jaw: the face below the mouth line (fully from 0.08 rad below it), across
// the chin and the jaw's front (fully within 0.5 rad of the midline, none beyond 1.1 rad). An anatomical guess of the
// template's own, not the simulator's blendshape.
float JawWeight(const Eigen::Vector2f& head_uv, const HeadLandmarks& landmarks) {
  const float azimuth = (head_uv.x() - 0.5f) * 2 * kPi, elevation = (head_uv.y() - 0.5f) * kPi;
  auto ramp = [](float e0, float e1, float x) { return std::clamp((x - e0) / (e1 - e0), 0.0f, 1.0f); };
  const float below = ramp(landmarks.mouth_elevation + 0.01f, landmarks.mouth_elevation - 0.08f, elevation);
  const float front = ramp(1.1f, 0.5f, std::abs(azimuth));
  const float w = below * front;
  return w * w * (3 - 2 * w);  // smoothstep
}

}  // namespace

FaceTemplateData MakeFaceTemplate(const HeadModel& head) {
  const TriangleMesh& m = head.neutral();
  auto inside = [](const Eigen::Vector2f& uv) {
    return uv.x() >= kULo - 1e-6f && uv.x() <= kUHi + 1e-6f && uv.y() >= kVLo - 1e-6f && uv.y() <= kVHi + 1e-6f;
  };
  FaceTemplateData t;
  t.u_lo = kULo;
  t.u_hi = kUHi;
  t.v_lo = kVLo;
  t.v_hi = kVHi;
  const HeadLandmarks landmarks = ProceduralHeadLandmarks();
  t.jaw_hinge_mm = landmarks.jaw_hinge_mm;
  t.jaw_axis = landmarks.jaw_axis;
  std::vector<int32_t> index(m.positions.size(), -1);
  for (size_t k = 0; k < m.triangles.size(); ++k) {
    if (!m.parts.empty() && m.parts[k] != 0) continue;  // skin only: the eyeballs are not the template's
    const auto& tri = m.triangles[k];
    if (!inside(m.uvs[tri[0]]) || !inside(m.uvs[tri[1]]) || !inside(m.uvs[tri[2]])) continue;
    std::array<int32_t, 3> out{};
    for (int c = 0; c < 3; ++c) {
      int32_t& i = index[static_cast<size_t>(tri[c])];
      if (i < 0) {
        i = static_cast<int32_t>(t.mesh.positions.size());
        const Eigen::Vector2f& uv = m.uvs[tri[c]];
        t.mesh.positions.push_back(m.positions[tri[c]]);
        t.mesh.uvs.emplace_back((uv.x() - kULo) / (kUHi - kULo), (uv.y() - kVLo) / (kVHi - kVLo));
        t.regions.push_back(RegionAt(uv, landmarks));
        t.jaw_weight.push_back(JawWeight(uv, landmarks));
        t.head_vertex.push_back(tri[c]);
      }
      out[c] = i;
    }
    t.mesh.triangles.push_back(out);
  }
  return t;
}

FaceModelData MakeFaceModel(const FaceTemplateData& face, const HeadModel& head, uint64_t first_identity,
                            int identities, int max_components, double variance_kept, int resolution) {
  FaceModelData model;
  if (identities <= 0 || max_components <= 0) return model;  // nothing to draw from (the caller checks)
  model.first_identity = first_identity;
  model.identities = identities;
  const size_t n = face.head_vertex.size();
  // The drawn faces' deviations from the template, one column each (x, y, z per vertex).
  Eigen::MatrixXd x(3 * static_cast<Eigen::Index>(n), identities);
  for (int k = 0; k < identities; ++k) {
    const auto drawn =
        HeadModel::Procedural(1, resolution, HeadShape::Drawn(first_identity + static_cast<uint64_t>(k)));
    const auto& positions = drawn->neutral().positions;
    if (positions.size() != head.neutral().positions.size()) return {};  // `head` is not at `resolution`
    for (size_t v = 0; v < n; ++v) {
      const Eigen::Vector3f d = positions[static_cast<size_t>(face.head_vertex[v])] - face.mesh.positions[v];
      x.block<3, 1>(3 * static_cast<Eigen::Index>(v), k) = d.cast<double>();
    }
  }
  // Principal components about the template (not about the drawn faces' mean: a coefficient of 0 is the template),
  // through the small Gram matrix.
  const Eigen::MatrixXd gram = x.transpose() * x / identities;
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(gram);
  const double total = std::max(eig.eigenvalues().sum(), 1e-30);
  double kept = 0;
  for (int k = identities - 1; k >= 0 && static_cast<int>(model.identity.size()) < max_components; --k) {
    const double lambda = eig.eigenvalues()(k);
    if (kept >= variance_kept || lambda <= 0) break;
    kept += lambda / total;
    // Unit direction X v / sqrt(N lambda), scaled by the standard deviation sqrt(lambda): X v / sqrt(N).
    const Eigen::VectorXd c = x * eig.eigenvectors().col(k) / std::sqrt(static_cast<double>(identities));
    std::vector<Eigen::Vector3f> component(n);
    for (size_t v = 0; v < n; ++v) component[v] = c.segment<3>(3 * static_cast<Eigen::Index>(v)).cast<float>();
    model.identity.push_back(std::move(component));
    model.identity_variance_share.push_back(lambda / total);
  }
  // The shipped head's blendshapes, each at weight 1 with the head unmoved.
  const auto& neutral = head.neutral().positions;
  for (int e = 0; e < kExpressionCount; ++e) {
    HeadPose pose;
    pose.expression[static_cast<size_t>(e)] = 1;
    const TriangleMesh posed = head.PosedMesh(pose);
    std::vector<Eigen::Vector3f> delta(n);
    for (size_t v = 0; v < n; ++v) {
      const auto h = static_cast<size_t>(face.head_vertex[v]);
      delta[v] = posed.positions[h] - neutral[h];
    }
    model.expression.push_back(std::move(delta));
  }
  return model;
}

namespace {

absl::Status WriteFaceModel(const FaceModelData& model, const std::string& path) {
  static_assert(std::endian::native == std::endian::little, "face-model.f32 is little-endian");
  std::ofstream out(path, std::ios::binary);
  for (const auto* set : {&model.identity, &model.expression}) {
    for (const auto& component : *set) {
      for (const Eigen::Vector3f& d : component) out.write(reinterpret_cast<const char*>(d.data()), 3 * sizeof(float));
    }
  }
  if (!out) return absl::UnavailableError(absl::StrCat(path, ": cannot write"));
  return absl::OkStatus();
}

}  // namespace

absl::Status WriteFaceTemplate(const FaceTemplateData& data, const std::string& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  const std::string comment =
      "FaStage face template: the shipped procedural head's face, neutral, head frame, mm (docs/assets.md)";
  if (auto s = WriteObj(dir + "/face-template.obj", data.mesh, comment); !s.ok()) return s;
  nlohmann::ordered_json j;
  j["format"] = "fastage-face-template";
  j["version"] = 1;
  j["source"] = "the simulator's procedural head (identity 0), stage-sim --export-face-template";
  j["mesh"] = "face-template.obj";
  auto rounded = [](float x) { return std::round(static_cast<double>(x) * 1e6) / 1e6; };
  j["head_layout_window"] = {{"u", {rounded(data.u_lo), rounded(data.u_hi)}},
                             {"v", {rounded(data.v_lo), rounded(data.v_hi)}}};
  std::vector<int> eyes, mouth;
  for (size_t v = 0; v < data.regions.size(); ++v) {
    if (data.regions[v] == TemplateRegion::kEye) eyes.push_back(static_cast<int>(v));
    if (data.regions[v] == TemplateRegion::kMouth) mouth.push_back(static_cast<int>(v));
  }
  j["regions"] = {{"eyes", eyes}, {"mouth", mouth}};
  std::vector<int> jaw_vertices;
  std::vector<double> jaw_weights;
  for (size_t v = 0; v < data.jaw_weight.size(); ++v) {
    if (data.jaw_weight[v] <= 0) continue;
    jaw_vertices.push_back(static_cast<int>(v));
    jaw_weights.push_back(std::round(static_cast<double>(data.jaw_weight[v]) * 1e4) / 1e4);
  }
  j["jaw"] = {{"hinge_mm", {data.jaw_hinge_mm.x(), data.jaw_hinge_mm.y(), data.jaw_hinge_mm.z()}},
              {"axis", {data.jaw_axis.x(), data.jaw_axis.y(), data.jaw_axis.z()}},
              {"vertices", jaw_vertices},
              {"weights", jaw_weights}};
  if (!data.model.identity.empty() || !data.model.expression.empty()) {
    const FaceModelData& m = data.model;
    if (auto s = WriteFaceModel(m, dir + "/face-model.f32"); !s.ok()) return s;
    std::vector<std::string> expressions;
    for (size_t e = 0; e < m.expression.size(); ++e) expressions.emplace_back(ExpressionName(static_cast<int>(e)));
    std::vector<double> shares;
    for (double s : m.identity_variance_share) shares.push_back(std::round(s * 1e6) / 1e6);
    j["model"] = {{"file", "face-model.f32"},
                  {"vertices", data.mesh.positions.size()},
                  {"identity_components", m.identity.size()},
                  {"identity_variance_share", shares},
                  {"identity_source", absl::StrCat("principal components of the neutral faces of the simulator's "
                                                   "performers ",
                                                   m.first_identity, "..", m.first_identity + m.identities - 1,
                                                   " about the template, each at one standard deviation")},
                  {"expressions", expressions},
                  {"expression_source", "the simulator's shipped head's blendshapes, each at weight 1"}};
  }
  const std::string path = dir + "/face-template.json";
  std::ofstream out(path);
  out << j.dump() << "\n";
  if (!out) return absl::UnavailableError(absl::StrCat(path, ": cannot write"));
  return absl::OkStatus();
}

}  // namespace stage::sim
