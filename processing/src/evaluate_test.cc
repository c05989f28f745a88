// EvaluatePhotometric: every map against the truth, over all compared pixels and over the confident ones (those the
// solver did not flag), saying how many that leaves out.
#include "stage/processing/evaluate.h"

#include <cmath>
#include <filesystem>
#include <fstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/processing/map_files.h"
#include "stage/processing/photometric_stage.h"

namespace stage::processing {
namespace {

Image Filled(int w, int h, int channels, std::vector<float> value) {
  Image image(w, h, channels);
  for (size_t i = 0; i < image.pixels.size(); ++i) image.pixels[i] = value[i % static_cast<size_t>(channels)];
  return image;
}

constexpr int kW = 4, kH = 4;

// A unit of 4 x 4 pixels whose albedo is right (0.5) but at one pixel, (2, 1), which the solver flagged a bad fit and
// whose albedo is 40 % off; its truth beside it (the surface 100 mm in front of the camera).
void WriteUnit(const std::string& results, const std::string& truth) {
  PhotometricMaps m;
  m.width = kW;
  m.height = kH;
  m.diffuse_normal_world = Filled(kW, kH, 3, {0, 0, 1});
  m.diffuse_normal_camera = m.diffuse_normal_world;
  m.albedo = Filled(kW, kH, 3, {0.5f, 0.5f, 0.5f});
  m.albedo.at(2, 1)[0] = m.albedo.at(2, 1)[1] = m.albedo.at(2, 1)[2] = 0.7f;
  m.specular_normal_world = Filled(kW, kH, 3, {0, 0, 1});
  m.specular_normal_camera = m.specular_normal_world;
  m.specular_normal_raw = m.specular_normal_world;
  m.specular = Filled(kW, kH, 1, {0.03f});
  m.roughness = Filled(kW, kH, 1, {0.3f});
  m.specular_sigma = Filled(kW, kH, 1, {1});
  m.confidence = Filled(kW, kH, 1, {1});
  m.fit_residual = Filled(kW, kH, 1, {1});
  m.flags.assign(kW * kH, 0);
  m.flags[1 * kW + 2] = kBadFit;
  ASSERT_TRUE(WriteMapFiles(UnitDir(results, 0, "hs-2"), m, "{}", "test").ok());
  const std::string unit = UnitDir(truth, 0, "hs-2");
  std::filesystem::create_directories(unit);
  ASSERT_TRUE(WriteExr(unit + "/normal_world.exr", Filled(kW, kH, 3, {0, 0, 1})).ok());
  ASSERT_TRUE(WriteExr(unit + "/albedo.exr", Filled(kW, kH, 3, {0.5f, 0.5f, 0.5f})).ok());
  ASSERT_TRUE(WriteExr(unit + "/specular.exr", Filled(kW, kH, 1, {0.03f})).ok());
  ASSERT_TRUE(WriteExr(unit + "/roughness.exr", Filled(kW, kH, 1, {0.3f})).ok());
  ASSERT_TRUE(WriteExr(unit + "/depth.exr", Filled(kW, kH, 1, {100})).ok());
  {
    // The subject mask: every pixel (a PGM; the image reader goes by the content, not the name).
    std::ofstream mask(unit + "/mask.png", std::ios::binary);
    mask << "P5\n" << kW << " " << kH << "\n255\n" << std::string(kW * kH, '\xff');
  }
}

const MapError* Albedo(const Evaluation& e) {
  for (const MapError& map : e.maps) {
    if (map.map == "albedo") return &map;
  }
  return nullptr;
}

TEST(EvaluateTest, ConfidentFiguresLeaveOutThePixelsTheSolverFlagged) {
  const std::string root = ::testing::TempDir() + "/evaluate-confident";
  std::filesystem::remove_all(root);
  const std::string results = root + "/results", truth = root + "/truth";
  WriteUnit(results, truth);
  EvaluateOptions options;
  options.results_dir = results;
  options.truth_dir = truth;
  auto e = EvaluatePhotometric(options);
  ASSERT_TRUE(e.ok()) << e.status();
  const MapError* albedo = Albedo(*e);
  ASSERT_NE(albedo, nullptr);
  EXPECT_EQ(albedo->pixels, kW * kH);
  EXPECT_NEAR(albedo->mean, 40.0 / (kW * kH), 1e-4);  // one pixel 40 % off among 16
  EXPECT_EQ(albedo->confident_pixels, kW * kH - 1);
  EXPECT_EQ(albedo->left_out, 1);
  EXPECT_NEAR(albedo->confident_mean, 0, 1e-4);
  EXPECT_THAT(FormatEvaluation(*e), ::testing::HasSubstr("confident: mean, median (left out)"));
  EXPECT_THAT(EvaluationJson(*e), ::testing::HasSubstr("\"left_out\": 1"));
  EXPECT_TRUE(e->by_geometry.empty());  // solved without geometry: nothing to split by
}

// The geometry a run was solved with (the surface at z = 100 mm): the pixel with the wrong albedo had its point 1 mm
// off the truth; one pixel was placed beyond the mesh, one had no point. The figures split by it, from the results'
// own geometry files or from another run's.
TEST(EvaluateTest, FiguresSplitByTheGeometryEachPixelWasSolvedWith) {
  const std::string root = ::testing::TempDir() + "/evaluate-geometry";
  std::filesystem::remove_all(root);
  const std::string results = root + "/results", truth = root + "/truth", other = root + "/other";
  WriteUnit(results, truth);
  PhotometricCamera camera;  // at the origin, looking along +z
  camera.position_mm.setZero();
  PixelGeometry g;
  g.width = kW;
  g.height = kH;
  g.points.resize(3 * kW * kH);
  for (int i = 0; i < kW * kH; ++i) {
    g.points[3 * i] = static_cast<float>(i % kW);
    g.points[3 * i + 1] = static_cast<float>(i / kW);
    g.points[3 * i + 2] = i == 1 * kW + 2 ? 101.f : 100.f;
  }
  g.points[0] = std::nanf("");  // pixel (0, 0): no point
  g.placed.assign(kW * kH, 0);
  g.placed[1] = 1;  // pixel (1, 0): placed beyond the mesh
  ASSERT_TRUE(WriteGeometryFiles(UnitDir(other, 0, "hs-2"), g, camera).ok());

  EvaluateOptions options;
  options.results_dir = results;
  options.truth_dir = truth;
  options.geometry_from = other;
  auto from_other = EvaluatePhotometric(options);
  ASSERT_TRUE(from_other.ok()) << from_other.status();
  ASSERT_TRUE(WriteGeometryFiles(UnitDir(results, 0, "hs-2"), g, camera).ok());
  options.geometry_from.clear();
  auto own = EvaluatePhotometric(options);
  ASSERT_TRUE(own.ok()) << own.status();
  for (const Evaluation* e : {&*from_other, &*own}) {
    ASSERT_EQ(e->by_geometry.size(), static_cast<size_t>(kGeometryClasses));
    const size_t albedo = static_cast<size_t>(Albedo(*e) - e->maps.data());
    const GeometrySplit& on = e->by_geometry[static_cast<int>(GeometryClass::kOnMesh)];
    const GeometrySplit& off = e->by_geometry[static_cast<int>(GeometryClass::kOffMesh)];
    EXPECT_EQ(on.mask_pixels, kW * kH - 3);
    EXPECT_EQ(off.mask_pixels, 1);
    EXPECT_EQ(e->by_geometry[static_cast<int>(GeometryClass::kPlacedOn)].mask_pixels, 1);
    EXPECT_EQ(e->by_geometry[static_cast<int>(GeometryClass::kPlacedOff)].mask_pixels, 0);
    EXPECT_EQ(e->by_geometry[static_cast<int>(GeometryClass::kNone)].mask_pixels, 1);
    EXPECT_NEAR(off.depth_error_median, 1.0, 1e-4);
    EXPECT_NEAR(on.depth_error_median, 0.0, 1e-4);
    EXPECT_NEAR(off.maps[albedo].mean, 40.0, 1e-3);  // the wrong albedo is all the error, and all of it is there
    EXPECT_NEAR(off.maps[albedo].share, 1.0, 1e-6);
    EXPECT_NEAR(on.maps[albedo].mean, 0.0, 1e-4);
    EXPECT_EQ(on.maps[albedo].pixels, kW * kH - 3);
    EXPECT_THAT(FormatEvaluation(*e), ::testing::HasSubstr("placed, off"));
    EXPECT_THAT(EvaluationJson(*e), ::testing::HasSubstr("\"geometry\": \"on the mesh, off\""));
  }
  EXPECT_EQ(from_other->geometry_from, other);
  EXPECT_EQ(own->geometry_from, results);
  {
    // A background pixel (out of the subject mask) is in no class.
    std::ofstream mask(UnitDir(truth, 0, "hs-2") + "/mask.png", std::ios::binary);
    mask << "P5\n" << kW << " " << kH << "\n255\n" << std::string(kW * kH - 1, '\xff') << '\0';
  }
  auto background = EvaluatePhotometric(options);
  ASSERT_TRUE(background.ok()) << background.status();
  int64_t classified = 0;
  for (const GeometrySplit& split : background->by_geometry) classified += split.mask_pixels;
  EXPECT_EQ(classified, kW * kH - 1);
  EXPECT_EQ(background->by_geometry[static_cast<int>(GeometryClass::kOnMesh)].mask_pixels, kW * kH - 4);

  EvaluateOptions bad = options;
  bad.geometry_off_mm = 0;
  EXPECT_THAT(std::string(EvaluatePhotometric(bad).status().message()), ::testing::HasSubstr("geometry_off_mm"));

  // A run named for the split that has no geometry files is an error that names the file.
  options.geometry_from = root + "/missing";
  auto missing = EvaluatePhotometric(options);
  ASSERT_FALSE(missing.ok());
  EXPECT_THAT(std::string(missing.status().message()), ::testing::HasSubstr("geometry_depth.exr"));
}

}  // namespace
}  // namespace stage::processing
