#include "stage/processing/face_template.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>

#include "stage/processing/template_fit.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

TEST(FaceTemplateTest, TheShippedTemplateIsAFaceWithItsRegions) {
  auto t = ShippedFaceTemplate();
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_GT(t->mesh.positions.size(), 9000u);
  ASSERT_EQ(t->regions.size(), t->mesh.positions.size());
  // Head frame: the face looks along +z, the template spans the front of the head, ear to ear but for the ears.
  Eigen::Vector3f lo = t->mesh.positions[0], hi = lo;
  for (const auto& p : t->mesh.positions) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  EXPECT_GT(hi.z(), 100);  // the nose's tip, in front of the head's centre
  EXPECT_GT(hi.x() - lo.x(), 120);
  EXPECT_LT(hi.x() - lo.x(), 200);
  for (const auto& uv : t->mesh.uvs) {
    ASSERT_GE(uv.minCoeff(), -1e-6f);
    ASSERT_LE(uv.maxCoeff(), 1 + 1e-6f);
  }
  EXPECT_NEAR(t->HeadLayoutUv({0, 0}).x(), 0.28f, 1e-6);
  EXPECT_NEAR(t->HeadLayoutUv({1, 1}).y(), 0.78f, 1e-6);
  // The jaw: the lower face follows it, the forehead not.
  int jaw = 0;
  for (size_t v = 0; v < t->jaw_weight.size(); ++v) {
    if (t->jaw_weight[v] > 0.99f) {
      ++jaw;
      EXPECT_LT(t->mesh.positions[v].y(), -40) << v;
    }
  }
  EXPECT_GT(jaw, 300);
}

TEST(FaceTemplateTest, TheShippedTemplateCarriesAShapeAndExpressionModel) {
  auto t = ShippedFaceTemplate();
  ASSERT_TRUE(t.ok()) << t.status();
  // Identity: the components of the drawn performers' faces, the first the largest, each a few millimetres at one
  // standard deviation somewhere on the face.
  ASSERT_GE(t->identity_basis.size(), 8u);
  auto largest = [](const std::vector<Eigen::Vector3f>& d) {
    float m = 0;
    for (const auto& v : d) m = std::max(m, v.norm());
    return m;
  };
  EXPECT_GT(largest(t->identity_basis[0]), 2.0f);
  EXPECT_LT(largest(t->identity_basis[0]), 30.0f);
  EXPECT_GT(largest(t->identity_basis[0]), largest(t->identity_basis.back()));
  // Expressions: named; the jaw's opening moves the chin down, not the forehead.
  ASSERT_EQ(t->expression_basis.size(), t->expression_names.size());
  const auto jaw = std::find(t->expression_names.begin(), t->expression_names.end(), "jaw_open");
  ASSERT_NE(jaw, t->expression_names.end());
  const auto& open = t->expression_basis[static_cast<size_t>(jaw - t->expression_names.begin())];
  float chin = 0, forehead = 0;
  for (size_t v = 0; v < open.size(); ++v) {
    if (t->mesh.positions[v].y() < -70) chin = std::min(chin, open[v].y());
    if (t->mesh.positions[v].y() > 60) forehead = std::max(forehead, open[v].norm());
  }
  EXPECT_LT(chin, -5.0f);
  EXPECT_LT(forehead, 0.01f);
}

TEST(FaceTemplateTest, ABrokenDescriptionIsRefusedNamingTheFileAndField) {
  const std::string dir = ::testing::TempDir();
  {
    std::ofstream obj(dir + "/t.obj");
    obj << "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n";
  }
  auto write_json = [&](const std::string& text) { std::ofstream(dir + "/t.json") << text; };
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0, 1], "v": [0, 1]},
                 "regions": {"eyes": [1], "mouth": [7]}})");
  auto far = LoadFaceTemplate(dir + "/t.obj");
  ASSERT_FALSE(far.ok());
  EXPECT_THAT(std::string(far.status().message()), HasSubstr(dir + "/t.json: regions.mouth: 7 is not a vertex"));
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0]}})");
  auto window = LoadFaceTemplate(dir + "/t.obj");
  EXPECT_THAT(std::string(window.status().message()), HasSubstr("head_layout_window"));
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0, 1], "v": [0, 1]},
                 "jaw": {"hinge_mm": [0, -20, -30], "axis": [1, 0, 0], "vertices": [0, 2], "weights": [1, 1.5]}})");
  EXPECT_THAT(std::string(LoadFaceTemplate(dir + "/t.obj").status().message()),
              HasSubstr("t.json: jaw.weights: 1.5 is not in [0, 1]"));
  write_json(R"({"format": "something else"})");
  EXPECT_THAT(std::string(LoadFaceTemplate(dir + "/t.obj").status().message()), HasSubstr("format"));
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0, 1], "v": [0, 1]},
                 "regions": {"eyes": [1]}})");
  auto good = LoadFaceTemplate(dir + "/t.obj");
  ASSERT_TRUE(good.ok()) << good.status();
  EXPECT_EQ(good->regions[1], FaceRegion::kEye);
  EXPECT_EQ(good->regions[0], FaceRegion::kSkin);
  EXPECT_EQ(good->jaw_weight, std::vector<float>(3, 0.0f));  // no jaw: the fit turns none
  EXPECT_EQ(LoadFaceTemplate(dir + "/none.obj").status().code(), absl::StatusCode::kNotFound);
  // A model whose file is not the size its description says.
  {
    std::ofstream model(dir + "/m.f32", std::ios::binary);
    const float zeros[9 * 2] = {};
    model.write(reinterpret_cast<const char*>(zeros), sizeof(zeros));
  }
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0, 1], "v": [0, 1]},
                 "model": {"file": "m.f32", "vertices": 3, "identity_components": 1, "expressions": ["a", "b"]}})");
  EXPECT_THAT(std::string(LoadFaceTemplate(dir + "/t.obj").status().message()),
              HasSubstr("t.json: model.file: m.f32 holds 72 bytes, not the 108"));
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0, 1], "v": [0, 1]},
                 "model": {"file": "m.f32", "vertices": 3, "identity_components": 1, "expressions": ["a"]}})");
  auto modelled = LoadFaceTemplate(dir + "/t.obj");
  ASSERT_TRUE(modelled.ok()) << modelled.status();
  EXPECT_EQ(modelled->identity_basis.size(), 1u);
  EXPECT_EQ(modelled->expression_names, std::vector<std::string>{"a"});
  write_json(R"({"format": "fastage-face-template", "version": 1, "head_layout_window": {"u": [0, 1], "v": [0, 1]},
                 "model": {"file": "gone.f32", "vertices": 3, "identity_components": 1, "expressions": []}})");
  EXPECT_THAT(std::string(LoadFaceTemplate(dir + "/t.obj").status().message()),
              HasSubstr("gone.f32: cannot read the template's model"));
}

}  // namespace
}  // namespace stage::processing

namespace stage::processing {
namespace {

TEST(TemplateFitTest, OptionsOutOfRangeAndAnEmptySurfaceAreRefused) {
  EXPECT_TRUE(TemplateFitOptions{}.Validate().ok());
  EXPECT_FALSE((TemplateFitOptions{.stiffness = {10, 0}}.Validate().ok()));
  EXPECT_FALSE(TemplateFitOptions{.iterations_per_stage = 0}.Validate().ok());
  EXPECT_FALSE(TemplateFitOptions{.max_distance_mm = -1}.Validate().ok());
  EXPECT_FALSE(TemplateFitOptions{.max_normal_angle_deg = 200}.Validate().ok());
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  const TemplateFit start = StartAt(*face, Eigen::Isometry3f::Identity());
  auto empty = FitTemplate(*face, TriangleMesh{}, start);
  EXPECT_THAT(std::string(empty.status().message()), HasSubstr("no triangles"));
  // A surface a metre away: no vertex finds it.
  TriangleMesh far;
  far.positions = {{0, 0, 1000}, {1, 0, 1000}, {0, 1, 1000}};
  far.triangles = {{{0, 1, 2}}};
  auto none = FitTemplate(*face, far, start);
  EXPECT_EQ(none.status().code(), absl::StatusCode::kNotFound) << none.status();
  EXPECT_FALSE(TemplateFitOptions{.model_iterations = -1}.Validate().ok());
  EXPECT_EQ(ParseNonRigidMotion("along_normal").value(), NonRigidMotion::kAlongNormal);
  EXPECT_THAT(std::string(ParseNonRigidMotion("sideways").status().message()),
              HasSubstr("\"sideways\" is not auto, free or along_normal"));
  EXPECT_FALSE(TemplateFitOptions{.identity_prior = -1}.Validate().ok());
  EXPECT_FALSE(TemplateFitOptions{.identity_reach = 0}.Validate().ok());
}

// A face the model makes (identity and expression coefficients, the head moved): the fit finds the coefficients and
// puts every vertex where it is on that face.
TEST(TemplateFitTest, TheModelsCoefficientsAreFoundOnAFaceItMade) {
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  ASSERT_GE(face->identity_basis.size(), 4u);
  std::vector<float> identity(face->identity_basis.size(), 0.0f), expression(face->expression_basis.size(), 0.0f);
  identity[0] = 1.2f;
  identity[1] = -0.8f;
  identity[3] = 0.5f;
  expression[1] = 0.6f;  // smile_left
  expression[0] = 0.3f;  // jaw_open
  TriangleMesh truth = face->mesh;
  const Eigen::Isometry3f pose = Eigen::Translation3f(2, -1, 3) * Eigen::AngleAxisf(0.05f, Eigen::Vector3f::UnitY());
  for (size_t v = 0; v < truth.positions.size(); ++v) {
    Eigen::Vector3f p = face->mesh.positions[v];
    for (size_t k = 0; k < identity.size(); ++k) p += identity[k] * face->identity_basis[k][v];
    for (size_t k = 0; k < expression.size(); ++k) p += expression[k] * face->expression_basis[k][v];
    truth.positions[v] = pose * p;
  }
  auto fit = FitTemplate(*face, truth, StartAt(*face, Eigen::Isometry3f::Identity()));
  ASSERT_TRUE(fit.ok()) << fit.status();
  // With a model the fit leaves the scale alone (the identity's components carry the head's size), so the identity's
  // coefficients are unique.
  EXPECT_EQ(fit->scale, 1.0f);
  for (size_t k = 0; k < identity.size(); ++k) EXPECT_NEAR(fit->identity[k], identity[k], 0.05) << "identity " << k;
  for (size_t k = 0; k < expression.size(); ++k) {
    EXPECT_NEAR(fit->expression[k], expression[k], 0.05) << face->expression_names[k];
  }
  double sum = 0;
  int64_t n = 0;
  for (size_t v = 0; v < truth.positions.size(); ++v) {
    if (face->regions[v] != FaceRegion::kSkin) continue;
    sum += (fit->positions[v] - truth.positions[v]).squaredNorm();
    ++n;
  }
  EXPECT_LT(std::sqrt(sum / static_cast<double>(n)), 0.05);
  // Without the model the same fit lands on the surface but not on the same skin.
  auto bare = FitTemplate(*face, truth, StartAt(*face, Eigen::Isometry3f::Identity()), {.model_iterations = 0});
  ASSERT_TRUE(bare.ok());
  double bare_sum = 0;
  for (size_t v = 0; v < truth.positions.size(); ++v) {
    if (face->regions[v] == FaceRegion::kSkin) bare_sum += (bare->positions[v] - truth.positions[v]).squaredNorm();
  }
  EXPECT_GT(std::sqrt(bare_sum / static_cast<double>(n)), 0.3);
}

// A surface with a hole where the template's forehead is: the vertices over the hole find nothing to be drawn to (the
// hole's rim is left out) and keep the model's shape; keeping the rim, they are pulled to it.
TEST(TemplateFitTest, AHolesRimDrawsNoVertex) {
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  // The template's own face as the surface, with its texture seams split as an OBJ reader splits them (each triangle
  // its own corners: every edge then borders one triangle unless welded), and a hole cut in the forehead.
  TriangleMesh surface;
  auto in_hole = [&](const Eigen::Vector3f& p) { return p.y() > 45 && p.y() < 75 && std::abs(p.x()) < 20; };
  for (const auto& t : face->mesh.triangles) {
    const Eigen::Vector3f c =
        (face->mesh.positions[t[0]] + face->mesh.positions[t[1]] + face->mesh.positions[t[2]]) / 3;
    if (in_hole(c)) continue;
    const auto base = static_cast<int32_t>(surface.positions.size());
    for (int k = 0; k < 3; ++k) surface.positions.push_back(face->mesh.positions[t[k]]);
    surface.triangles.push_back({base, base + 1, base + 2});
  }
  auto error_over_hole = [&](const TemplateFit& fit) {
    double sum = 0;
    int n = 0;
    for (size_t v = 0; v < fit.positions.size(); ++v) {
      if (!in_hole(face->mesh.positions[v])) continue;
      sum += (fit.positions[v] - face->mesh.positions[v]).squaredNorm();
      ++n;
    }
    EXPECT_GT(n, 30);
    return std::sqrt(sum / std::max(n, 1));
  };
  const TemplateFit start = StartAt(*face, Eigen::Isometry3f::Identity());
  auto skipped = FitTemplate(*face, surface, start);
  ASSERT_TRUE(skipped.ok()) << skipped.status();
  auto kept = FitTemplate(*face, surface, start, {.skip_border = false, .nonrigid = NonRigidMotion::kFree});
  ASSERT_TRUE(kept.ok()) << kept.status();
  // Split seams are no border: the rest of the face is matched (all but the hole, its rim and the face's own edge).
  EXPECT_GT(skipped->matched, static_cast<int64_t>(face->mesh.positions.size() * 8 / 10));
  EXPECT_LT(error_over_hole(*skipped), 0.05);
  EXPECT_GT(error_over_hole(*kept), 2 * error_over_hole(*skipped));
}

}  // namespace
}  // namespace stage::processing
