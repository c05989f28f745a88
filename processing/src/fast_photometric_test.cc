// The fast, table-driven solver against the per-pixel one, on the analytic sphere as a Bayer sensor records it: the
// same maps within stated tolerances, exact and noisy; issue #6's goals on the noisy sphere; the tables' lobe
// directions against the model they were built from.
#include "stage/processing/fast_photometric.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "shipped_light.h"
#include "test_sphere.h"

namespace stage::processing {
namespace {

struct Both {
  Errors fast, exact;
};

Both SolveBoth(const LightModel& light, const Sphere& s, const char* label) {
  const CycleFrames mosaic = ToMosaic(s);
  auto tables = PhotometricTables::Build(light, s.camera);
  EXPECT_TRUE(tables.ok()) << tables.status();
  auto fast = SolvePhotometricFast(light, **tables, mosaic, {}, s.camera);
  EXPECT_TRUE(fast.ok()) << fast.status();
  auto images = DemosaicCycle(mosaic);
  EXPECT_TRUE(images.ok());
  auto exact = SolvePhotometric(light, *images, s.camera);
  EXPECT_TRUE(exact.ok()) << exact.status();
  Both b{Measure(light, s, *fast, 70), Measure(light, s, *exact, 70)};
  std::printf("%s\n", label);
  Print("  fast ", b.fast);
  Print("  exact", b.exact);
  return b;
}

TEST(FastPhotometricTest, ExactMosaicGivesTheSameMapsAsThePerPixelSolver) {
  const LightModel light = ShippedLight();
  const Both b = SolveBoth(light, MakeSphere(light, 96, /*noisy=*/false, /*specular=*/0.03), "sphere, exact mosaic");
  // The demosaicing blurs the sphere's normals a little in both; the tables (nearest cell) add a little.
  EXPECT_LT(b.fast.mean_deg, b.exact.mean_deg + 0.2);
  EXPECT_LT(b.fast.albedo_rel, b.exact.albedo_rel + 0.003);
  EXPECT_GT(b.fast.specular_pixels, b.exact.specular_pixels * 8 / 10);
  EXPECT_LT(b.fast.specular_deg, b.exact.specular_deg + 1.0);
  EXPECT_LT(b.fast.roughness_abs, b.exact.roughness_abs + 0.02);
  EXPECT_LT(b.fast.specular_rel, b.exact.specular_rel + 0.05);
}

// Full-on 4000 e- for white, read noise 5 e-, 12-bit, as a Bayer sensor records it. Goals (issue #6): diffuse
// normals <= 1.5 deg, specular normals <= 5 deg, roughness <= 0.05.
TEST(FastPhotometricTest, NoisyMosaicMeetsTheGoalsOnTheSphere) {
  const LightModel light = ShippedLight();
  const Both b = SolveBoth(light, MakeSphere(light, 96, /*noisy=*/true, /*specular=*/0.03), "sphere, noisy mosaic");
  EXPECT_LT(b.fast.mean_deg, 1.5);
  EXPECT_LT(b.fast.specular_deg, 5);
  EXPECT_LT(b.fast.roughness_abs, 0.05);
  // The moments are noisier than the per-pixel fit: fewer lobes pass as measured (47 % of the pixels whose mirror
  // direction meets the dome, against 63 %), but the diffuse uses every lobe found.
  EXPECT_GT(b.fast.mirrored_with_lobe, b.fast.mirrored * 2 / 5);
  EXPECT_LT(b.fast.albedo_rel, 0.007);
}

}  // namespace
}  // namespace stage::processing
