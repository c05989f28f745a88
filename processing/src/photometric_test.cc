// Photometric stereo on an analytic sphere: images made from the light model in closed form (a Lambertian sphere
// under the shipped rig's 168 units and 38 patterns, seen from +z), with and without the sensor's noise (full-on 4000
// e-, read noise 5 e-, 12-bit). The solver must return the sphere's normals and albedo; a mislabeled pattern must
// raise the error and be flagged.
#include "stage/processing/photometric.h"

#include <random>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "shipped_light.h"
#include "stage/common/rig.h"

namespace stage::processing {
namespace {

struct Sphere {
  std::vector<Image> frames;
  std::vector<Eigen::Vector3d> normals;  // per pixel; zero outside
  PhotometricCamera camera;
  int size = 0;
};

const Eigen::Vector3d kAlbedo(0.6, 0.45, 0.35);

// A sphere filling `size` x `size` pixels, seen orthographically from +z (its normal at pixel (x, y) is (sx, -sy,
// sqrt(1 - sx^2 - sy^2)) with sx, sy in [-1, 1]; image y runs down). Full-on white reads `white_full_e` electrons.
Sphere MakeSphere(const LightModel& light, int size, bool noisy, double white_full_e = 4000) {
  Sphere s;
  s.size = size;
  // Calibrated so that a white patch facing +z under cross full-on reads white_full_e electrons; 12-bit, full well
  // 10000 e-.
  const double full =
      light.DiffuseVector(*light.Find("cross-full"), Eigen::Vector3d::UnitZ()).dot(Eigen::Vector3d::UnitZ());
  s.camera.gain_e_per_dn = 10000.0 / 4095.0;
  s.camera.white_scale = white_full_e / s.camera.gain_e_per_dn / full;
  s.camera.read_noise_e = 5;
  s.camera.saturation_dn = 4095;
  s.camera.world_to_camera = Eigen::Vector3d(1, -1, -1).asDiagonal();  // looking down -z from +z, y down
  s.frames.assign(light.patterns.size(), Image(size, size, 3));
  s.normals.assign(static_cast<size_t>(size) * size, Eigen::Vector3d::Zero());
  std::mt19937 rng(7);
  std::normal_distribution<double> gauss(0, 1);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double sx = (x + 0.5) / size * 2 - 1, sy = -((y + 0.5) / size * 2 - 1);
      const double r2 = sx * sx + sy * sy;
      if (r2 >= 0.98) continue;
      const Eigen::Vector3d n(sx, sy, std::sqrt(1 - r2));
      s.normals[static_cast<size_t>(y) * size + x] = n;
      for (size_t p = 0; p < light.patterns.size(); ++p) {
        const double shade = n.dot(light.DiffuseVector(static_cast<int>(p), n));
        for (int c = 0; c < 3; ++c) {
          double dn = s.camera.white_scale * kAlbedo[c] * shade;
          if (noisy) {
            const double e = dn * s.camera.gain_e_per_dn;
            dn = std::round((e + std::sqrt(e + 25.0) * gauss(rng)) / s.camera.gain_e_per_dn);
          }
          s.frames[p].at(x, y)[c] = static_cast<float>(std::clamp(dn, 0.0, 4095.0));
        }
      }
    }
  }
  return s;
}

struct Errors {
  double mean_deg = 0, max_deg = 0, albedo_rel = 0;
  int pixels = 0;
};

Errors Measure(const Sphere& s, const PhotometricMaps& m, double max_tilt_deg) {
  Errors e;
  for (int y = 0; y < s.size; ++y) {
    for (int x = 0; x < s.size; ++x) {
      const Eigen::Vector3d& truth = s.normals[static_cast<size_t>(y) * s.size + x];
      if (truth.isZero() || AngleDeg(truth, Eigen::Vector3d::UnitZ()) > max_tilt_deg) continue;
      const float* n = m.diffuse_normal_world.at(x, y);
      const double err = AngleDeg(truth, Eigen::Vector3d(n[0], n[1], n[2]));
      e.mean_deg += err;
      e.max_deg = std::max(e.max_deg, err);
      const float* a = m.albedo.at(x, y);
      for (int c = 0; c < 3; ++c) e.albedo_rel += std::abs(a[c] / kAlbedo[c] - 1) / 3;
      ++e.pixels;
    }
  }
  e.mean_deg /= std::max(1, e.pixels);
  e.albedo_rel /= std::max(1, e.pixels);
  return e;
}

TEST(PhotometricTest, ExactImagesGiveTheSpheresNormalsAndAlbedo) {
  const LightModel light = ShippedLight();
  ASSERT_EQ(light.patterns.size(), 38u);
  const Sphere s = MakeSphere(light, 96, /*noisy=*/false);
  auto m = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(m.ok()) << m.status();
  // Facing the camera up to 70 degrees: only the table's interpolation separates the result from the truth.
  const Errors e = Measure(s, *m, 70);
  EXPECT_GT(e.pixels, 5000);
  EXPECT_LT(e.mean_deg, 0.1);
  EXPECT_LT(e.max_deg, 1.0);
  EXPECT_LT(e.albedo_rel, 0.002);
  // The camera frame: the sphere's centre faces the camera (z towards it is -z in the camera frame).
  const float* centre = m->diffuse_normal_camera.at(48, 48);
  EXPECT_LT(centre[2], -0.99);
}

// Full-on 4000 e-, read noise 5 e-, 12-bit. Goals (issue #6): mean normal error <= 1.5 deg, albedo <= 0.7 %. The
// albedo is not there yet (0.89 % over the disk up to 70 degrees of tilt): this bounds what is reached so far.
TEST(PhotometricTest, NoisyImagesAreCloseToTheSphere) {
  const LightModel light = ShippedLight();
  const Sphere s = MakeSphere(light, 96, /*noisy=*/true);
  auto m = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(m.ok()) << m.status();
  const Errors e = Measure(s, *m, 70);
  std::printf("sphere, noisy: mean %.3f deg, max %.3f deg, albedo %.3f %% over %d pixels\n", e.mean_deg, e.max_deg,
              100 * e.albedo_rel, e.pixels);
  EXPECT_LT(e.mean_deg, 1.5);
  EXPECT_LT(e.albedo_rel, 0.010);
}

// x+ and x- swapped (a sequencing error): the normals turn wrong and the fit says so.
TEST(PhotometricTest, AMislabeledPatternRaisesTheErrorAndIsFlagged) {
  const LightModel light = ShippedLight();
  Sphere s = MakeSphere(light, 64, /*noisy=*/true);
  auto good = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(good.ok());
  const int xp = *light.Find("cross-x+"), xm = *light.Find("cross-x-");
  std::swap(s.frames[static_cast<size_t>(xp)], s.frames[static_cast<size_t>(xm)]);
  auto bad = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(bad.ok());
  const Errors eg = Measure(s, *good, 70), eb = Measure(s, *bad, 70);
  EXPECT_GT(eb.mean_deg, 5 * eg.mean_deg);
  int flagged_good = 0, flagged_bad = 0;
  double conf_good = 0, conf_bad = 0;
  for (size_t i = 0; i < good->flags.size(); ++i) {
    if (s.normals[i].isZero()) continue;
    flagged_good += (good->flags[i] & kBadFit) != 0;
    flagged_bad += (bad->flags[i] & kBadFit) != 0;
    conf_good += good->confidence.pixels[i];
    conf_bad += bad->confidence.pixels[i];
  }
  EXPECT_GT(flagged_bad, 10 * std::max(1, flagged_good));
  EXPECT_LT(conf_bad, 0.5 * conf_good);
}

TEST(PhotometricTest, BadInputIsNamed) {
  const LightModel light = ShippedLight();
  std::vector<Image> frames(light.patterns.size(), Image(8, 8, 3));
  frames[5] = Image(8, 4, 3);
  auto m = SolvePhotometric(light, frames, PhotometricCamera());
  ASSERT_FALSE(m.ok());
  EXPECT_THAT(m.status().message(), ::testing::HasSubstr(light.patterns[5].name));
  frames.pop_back();
  EXPECT_FALSE(SolvePhotometric(light, frames, PhotometricCamera()).ok());
}

}  // namespace
}  // namespace stage::processing
