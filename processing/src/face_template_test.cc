#include "stage/processing/face_template.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

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
}

}  // namespace
}  // namespace stage::processing
