// EvaluatePhotometric: every map against the truth, over all compared pixels and over the confident ones (those the
// solver did not flag), saying how many that leaves out.
#include "stage/processing/evaluate.h"

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

// A unit of 4 x 4 pixels whose albedo is right (0.5) but at one pixel, which the solver flagged a bad fit and whose
// albedo is 40 % off; its truth beside it.
TEST(EvaluateTest, ConfidentFiguresLeaveOutThePixelsTheSolverFlagged) {
  const std::string root = ::testing::TempDir() + "/evaluate-confident";
  std::filesystem::remove_all(root);
  const std::string results = root + "/results", truth = root + "/truth";
  constexpr int kW = 4, kH = 4;
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
  {
    // The subject mask: every pixel (a PGM; the image reader goes by the content, not the name).
    std::ofstream mask(unit + "/mask.png", std::ios::binary);
    mask << "P5\n" << kW << " " << kH << "\n255\n" << std::string(kW * kH, '\xff');
  }
  EvaluateOptions options;
  options.results_dir = results;
  options.truth_dir = truth;
  auto e = EvaluatePhotometric(options);
  ASSERT_TRUE(e.ok()) << e.status();
  const MapError* albedo = nullptr;
  for (const MapError& map : e->maps) {
    if (map.map == "albedo") albedo = &map;
  }
  ASSERT_NE(albedo, nullptr);
  EXPECT_EQ(albedo->pixels, kW * kH);
  EXPECT_NEAR(albedo->mean, 40.0 / (kW * kH), 1e-4);  // one pixel 40 % off among 16
  EXPECT_EQ(albedo->confident_pixels, kW * kH - 1);
  EXPECT_EQ(albedo->left_out, 1);
  EXPECT_NEAR(albedo->confident_mean, 0, 1e-4);
  EXPECT_THAT(FormatEvaluation(*e), ::testing::HasSubstr("confident: mean, median (left out)"));
  EXPECT_THAT(EvaluationJson(*e), ::testing::HasSubstr("\"left_out\": 1"));
}

}  // namespace
}  // namespace stage::processing
