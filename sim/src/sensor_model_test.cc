// The sensor model: noise statistics against the model within 2 %, determinism by seed, the Bayer mosaic, clipping.
#include "stage/sim/sensor_model.h"

#include <cmath>
#include <cstdio>

#include "gtest/gtest.h"

namespace stage::sim {
namespace {

struct Stats {
  double mean = 0, variance = 0;
};

Stats Measure(const RawImage& img) {
  double sum = 0, sum2 = 0;
  for (uint16_t v : img.data) {
    sum += v;
    sum2 += static_cast<double>(v) * v;
  }
  const double n = static_cast<double>(img.data.size());
  return {sum / n, sum2 / n - (sum / n) * (sum / n)};
}

TEST(SensorModelTest, MeanAndVarianceFollowTheModelWithinTwoPercent) {
  SensorParams p;
  p.mosaic = "mono";
  p.bits = 12;
  p.full_well_e = 20000;
  p.read_noise_e = 5;
  p.black_level_dn = 64;
  p.electrons_per_dn = 2.0;  // 12 bits reach 8062 e- above the black level
  p.electrons_per_radiance_s = 1e6;
  const int w = 256, h = 256;
  for (double signal : {30.0, 400.0, 4000.0}) {
    // Uniform grey radiance giving `signal` electrons in a 1 ms exposure (mono reads luminance = the grey level).
    const float radiance = static_cast<float>(signal / (p.electrons_per_radiance_s * 1e-3));
    std::vector<float> rgb(static_cast<size_t>(w) * h * 3, radiance);
    RawImage img = ExposeSensor(rgb, w, h, 1e-3, p, 11, 1, 0);
    Stats s = Measure(img);
    const double want_mean = p.black_level_dn + signal / p.Gain();
    // Shot noise (Poisson: variance = mean) plus read noise, in DN, plus the quantizer's 1/12 DN^2.
    const double want_var = (signal + p.read_noise_e * p.read_noise_e) / (p.Gain() * p.Gain()) + 1.0 / 12;
    std::printf("signal %6.0f e-: mean %.2f DN (model %.2f), variance %.2f DN^2 (model %.2f)\n", signal, s.mean,
                want_mean, s.variance, want_var);
    EXPECT_NEAR(s.mean, want_mean, 0.02 * (want_mean - p.black_level_dn)) << signal;
    EXPECT_NEAR(s.variance, want_var, 0.02 * want_var) << signal;
  }
}

TEST(SensorModelTest, SameSeedSameBytesDifferentSeedOrFrameDifferentNoise) {
  SensorParams p;
  p.electrons_per_radiance_s = 1e6;
  std::vector<float> rgb(64 * 48 * 3, 0.5f);
  RawImage a = ExposeSensor(rgb, 64, 48, 1e-3, p, 5, 9, 3);
  RawImage b = ExposeSensor(rgb, 64, 48, 1e-3, p, 5, 9, 3);
  EXPECT_EQ(a.data, b.data);
  EXPECT_NE(ExposeSensor(rgb, 64, 48, 1e-3, p, 6, 9, 3).data, a.data);  // another seed
  EXPECT_NE(ExposeSensor(rgb, 64, 48, 1e-3, p, 5, 9, 4).data, a.data);  // the next frame
  EXPECT_NE(ExposeSensor(rgb, 64, 48, 1e-3, p, 5, 8, 3).data, a.data);  // another camera
}

TEST(SensorModelTest, BayerMosaicAndClipping) {
  SensorParams p;
  p.read_noise_e = 0;
  p.electrons_per_radiance_s = 1e6;
  p.full_well_e = 1000;
  std::vector<float> red(8 * 8 * 3, 0.0f);
  for (size_t i = 0; i < 64; ++i) red[3 * i] = 0.5f;  // 500 e- in 1 ms
  RawImage img = ExposeSensor(red, 8, 8, 1e-3, p, 1, 1, 1);
  for (int y = 0; y < 8; ++y) {
    for (int x = 0; x < 8; ++x) {
      const uint16_t v = img.data[static_cast<size_t>(y) * 8 + x];
      if (MosaicColor("RG", x, y) == 0) {
        EXPECT_GT(v, 0) << x << "," << y;  // red pixels see it (RGGB: even row, even column)
      } else {
        EXPECT_EQ(v, 0) << x << "," << y;
      }
    }
  }
  EXPECT_EQ(MosaicColor("RG", 0, 0), 0);
  EXPECT_EQ(MosaicColor("RG", 1, 1), 2);
  EXPECT_EQ(MosaicColor("BG", 0, 0), 2);
  // Far beyond the full well: clipped to the top code.
  std::vector<float> bright(8 * 8 * 3, 100.0f);
  RawImage clipped = ExposeSensor(bright, 8, 8, 1e-3, p, 1, 1, 1);
  for (uint16_t v : clipped.data) EXPECT_EQ(v, 255);
}

}  // namespace
}  // namespace stage::sim
