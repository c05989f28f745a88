// LED emission over time: ramps, integrals, and the blend an exposure straddling a slot edge records.
#include "stage/sim/emission.h"

#include "gtest/gtest.h"

namespace stage::sim {
namespace {

TEST(ChannelWaveformTest, InstantStepsIntegrateExactly) {
  ChannelWaveform w;
  w.Step(100, 1.0);
  w.Step(300, 0.25);
  EXPECT_DOUBLE_EQ(w.At(99), 0);
  EXPECT_DOUBLE_EQ(w.At(100), 1);
  EXPECT_DOUBLE_EQ(w.At(300), 0.25);
  EXPECT_DOUBLE_EQ(w.Integral(0, 100), 0);
  EXPECT_DOUBLE_EQ(w.Integral(50, 150), 50);
  EXPECT_DOUBLE_EQ(w.Integral(200, 400), 100 + 25);
}

TEST(ChannelWaveformTest, RampsAtTheRiseAndFallTimes) {
  // Full scale in 10 ns up, 20 ns down.
  ChannelWaveform w(10, 20);
  w.Step(0, 1.0);
  EXPECT_DOUBLE_EQ(w.At(5), 0.5);
  EXPECT_DOUBLE_EQ(w.At(10), 1.0);
  EXPECT_DOUBLE_EQ(w.Integral(0, 20), 5 + 10);  // the ramp's triangle, then flat
  w.Step(100, 0.5);                             // down by half: 10 ns
  EXPECT_DOUBLE_EQ(w.At(105), 0.75);
  EXPECT_DOUBLE_EQ(w.At(110), 0.5);
  EXPECT_DOUBLE_EQ(w.Integral(100, 120), (1.0 + 0.5) / 2 * 10 + 0.5 * 10);
  // A step before the ramp has finished starts from where the output is.
  ChannelWaveform fast(100, 100);
  fast.Step(0, 1.0);
  fast.Step(50, 0.0);  // reached 0.5, falls back from there
  EXPECT_DOUBLE_EQ(fast.At(50), 0.5);
  EXPECT_DOUBLE_EQ(fast.At(75), 0.25);
  EXPECT_DOUBLE_EQ(fast.At(100), 0.0);
  // Forgetting steps before t changes nothing from t on.
  const double before = w.Integral(100, 200);
  w.Forget(100);
  EXPECT_DOUBLE_EQ(w.Integral(100, 200), before);
  EXPECT_EQ(w.steps(), 1u);
}

// An exposure that straddles a slot edge by a fraction a of its length records (1 - a) of the first pattern and a
// of the second: the image is that blend of the two pattern images, exactly.
TEST(EmissionTest, AnExposureStraddlingASlotEdgeBlendsTheTwoPatterns) {
  Dome dome = Dome::FromDirections(FibonacciSphere(40), 1000, 1e6);
  EmissionState emission(dome, {0}, {0});
  // Pattern A lights the parallel emitters by x, pattern B the cross emitters by y.
  std::vector<double> a(80, 0.0), b(80, 0.0);
  for (size_t l = 0; l < 40; ++l) {
    a[dome.units[l].parallel_channel] = (1 + dome.units[l].direction.x()) / 2;
    b[dome.units[l].cross_channel] = (1 + dome.units[l].direction.y()) / 2;
  }
  const int64_t edge = 1'096'491;
  emission.SetLevels(0, 0, a);
  emission.SetLevels(0, edge, b);
  SphereSubject sphere(Eigen::Vector3f::Zero(), 100, Material{Eigen::Vector3f(0.5f, 0.4f, 0.3f), 0.04f, 0.3f});
  v1::CameraConfig c;
  c.set_id("c");
  c.set_width(64);
  c.set_height(48);
  c.mutable_intrinsics()->set_focal_length_mm(35);
  c.mutable_intrinsics()->set_pixel_size_um(150);
  c.mutable_pose()->mutable_position_mm()->set_z(800);
  auto camera = CameraModel::FromConfig(c, 1.0);
  ASSERT_TRUE(camera.ok());
  PixelResponses r = ComputeResponses(*camera, sphere, dome);
  const float leak = 0.02f;
  const std::vector<float> image_a = RenderRadiance(r, emission.AverageLevels(100'000, 900'000), leak);
  const std::vector<float> image_b = RenderRadiance(r, emission.AverageLevels(1'200'000, 2'000'000), leak);
  const int64_t exposure = 800'000;
  for (double frac : {0.0, 0.25, 0.5, 0.9}) {
    const int64_t start = edge - static_cast<int64_t>((1 - frac) * exposure);
    const std::vector<float> blend = RenderRadiance(r, emission.AverageLevels(start, start + exposure), leak);
    for (size_t i = 0; i < blend.size(); ++i) {
      const float want = static_cast<float>((1 - frac) * image_a[i] + frac * image_b[i]);
      ASSERT_NEAR(blend[i], want, 1e-5f * (1 + want)) << "fraction " << frac << " value " << i;
    }
  }
}

TEST(EmissionTest, ADarkNodeLightsNothing) {
  std::vector<Eigen::Vector3d> dirs = FibonacciSphere(6);
  Dome dome = Dome::FromDirections(dirs, 1000);
  for (size_t l = 3; l < 6; ++l) {
    dome.units[l].node = 1;
    dome.units[l].parallel_channel -= 6;
    dome.units[l].cross_channel -= 6;
  }
  EmissionState emission(dome, {0, 0}, {0, 0});
  emission.SetLevels(0, 0, std::vector<double>(6, 1.0));
  emission.SetLevels(1, 0, std::vector<double>(6, 1.0));
  emission.Dark(1, 500);
  EmitterLevels l = emission.AverageLevels(1000, 2000);
  for (int u = 0; u < 3; ++u) EXPECT_FLOAT_EQ(l.parallel[u], 1.0f);
  for (int u = 3; u < 6; ++u) EXPECT_FLOAT_EQ(l.parallel[u], 0.0f);
  l = emission.AverageLevels(0, 1000);  // half the exposure before the node went dark
  EXPECT_FLOAT_EQ(l.cross[4], 0.5f);
}

}  // namespace
}  // namespace stage::sim
