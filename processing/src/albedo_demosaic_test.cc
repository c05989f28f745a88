// internal::DemosaicAlbedo: the colours a Bayer pixel does not measure, from its own albedo and its neighbours' hue.
#include <cmath>
#include <cstring>
#include <random>

#include "gtest/gtest.h"
#include "photometric_internal.h"

namespace stage::processing {
namespace {

// A skin-like albedo: a texture that darkens all three colours alike (pores, freckles) on a hue that changes sharply
// at column `edge` (skin to lips).
struct Field {
  int w = 0, h = 0;
  std::vector<Eigen::Vector3f> truth;
  std::vector<float> own;  // the colour each pixel measures (RGGB)
  PhotometricMaps maps;
};

Field MakeField(int w, int h, int edge) {
  Field f;
  f.w = w;
  f.h = h;
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> texture(0.75f, 1.f);
  const Mosaic mosaic;
  f.maps.width = w;
  f.maps.height = h;
  f.maps.albedo = Image(w, h, 3);
  f.maps.flags.assign(static_cast<size_t>(w) * h, 0);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Vector3f hue = x < edge ? Eigen::Vector3f(0.6f, 0.4f, 0.31f) : Eigen::Vector3f(0.52f, 0.22f, 0.22f);
      f.truth.push_back(hue * texture(rng));
      f.own.push_back(f.truth.back()[mosaic.Color(x, y)]);
    }
  }
  return f;
}

// Mean relative error of the colours the pixels do not measure, over columns [x0, x1) (rows 2 from the edges), as
// estimate(x, y, c) has them.
template <typename F>
double InterpolatedError(const Field& f, int x0, int x1, F estimate) {
  const Mosaic mosaic;
  double sum = 0;
  int n = 0;
  for (int y = 2; y < f.h - 2; ++y) {
    for (int x = x0; x < x1; ++x) {
      for (int c = 0; c < 3; ++c) {
        if (c == mosaic.Color(x, y)) continue;
        sum += std::abs(estimate(x, y, c) / f.truth[static_cast<size_t>(y) * f.w + x][c] - 1);
        ++n;
      }
    }
  }
  return sum / std::max(1, n);
}

// The demosaiced map's.
double InterpolatedError(const Field& f, int x0, int x1) {
  return InterpolatedError(f, x0, x1, [&](int x, int y, int c) { return f.maps.albedo.at(x, y)[c]; });
}

// The neighbours' mean alone (bilinear demosaicing of the albedo), for comparison: every missing colour the mean of
// the pixel's 8 neighbours of that colour.
double BilinearError(const Field& f, int x0, int x1) {
  const Mosaic mosaic;
  return InterpolatedError(f, x0, x1, [&](int x, int y, int c) {
    double s = 0;
    int k = 0;
    for (int dy = -1; dy <= 1; ++dy) {
      for (int dx = -1; dx <= 1; ++dx) {
        if (mosaic.Color(x + dx, y + dy) != c) continue;
        s += f.own[static_cast<size_t>(y + dy) * f.w + x + dx];
        ++k;
      }
    }
    return s / k;
  });
}

TEST(DemosaicAlbedoTest, KeepsTheTextureAndPassesOverAChangeOfHue) {
  Field f = MakeField(64, 40, 32);
  internal::DemosaicAlbedo(Mosaic{}, f.own.data(), 1.5f, 2, &f.maps);
  // The measured colour is the pixel's own.
  for (int y = 0; y < f.h; ++y) {
    for (int x = 0; x < f.w; ++x) {
      const size_t i = static_cast<size_t>(y) * f.w + x;
      ASSERT_EQ(f.maps.albedo.at(x, y)[Mosaic{}.Color(x, y)], f.own[i]) << x << "," << y;
    }
  }
  // Away from the change of hue: the texture is the pixel's own, blurred by the neighbours' 30 % share only (about
  // half the error of theirs alone).
  const double away = InterpolatedError(f, 2, 24), away_bilinear = BilinearError(f, 2, 24);
  EXPECT_LT(away, 0.6 * away_bilinear) << away << " against " << away_bilinear;
  // Within 4 columns of it: a window centred on the pixel mixes both hues; the pixel's least varying window does not.
  const double edge = InterpolatedError(f, 28, 36), edge_bilinear = BilinearError(f, 28, 36);
  EXPECT_LT(edge, 0.6 * edge_bilinear) << edge << " against " << edge_bilinear;
  EXPECT_LT(edge, 1.5 * away) << edge << " against " << away;
}

TEST(DemosaicAlbedoTest, UnsolvedPixelsAreZeroAndThreadsDoNotChangeTheBits) {
  Field f = MakeField(70, 150, 40);
  // A hole and a ragged edge not solved, an unsolved band of rows, and a pixel with no usable albedo.
  for (int y = 0; y < f.h; ++y) {
    for (int x = 0; x < f.w; ++x) {
      const bool hole = std::abs(x - 20) < 5 && std::abs(y - 30) < 7;
      if (hole || x > 60 - (y % 7) || (y >= 90 && y < 100)) f.maps.flags[static_cast<size_t>(y) * f.w + x] = kLowSignal;
    }
  }
  f.own[static_cast<size_t>(50) * f.w + 10] = 0;
  Field one = f;
  internal::DemosaicAlbedo(Mosaic{}, f.own.data(), 1.5f, 3, &f.maps);
  internal::DemosaicAlbedo(Mosaic{}, one.own.data(), 1.5f, 1, &one.maps);
  ASSERT_EQ(f.maps.albedo.pixels.size(), one.maps.albedo.pixels.size());
  EXPECT_EQ(std::memcmp(f.maps.albedo.pixels.data(), one.maps.albedo.pixels.data(),
                        f.maps.albedo.pixels.size() * sizeof(float)),
            0);
  int zero = 0, solved_nonzero = 0;
  for (int y = 0; y < f.h; ++y) {
    for (int x = 0; x < f.w; ++x) {
      const float* a = f.maps.albedo.at(x, y);
      if (f.maps.flags[static_cast<size_t>(y) * f.w + x] & kLowSignal) {
        zero += a[0] == 0 && a[1] == 0 && a[2] == 0;
      } else {
        solved_nonzero += a[0] > 0 && a[1] > 0 && a[2] > 0;
      }
    }
  }
  int unsolved = 0;
  for (uint8_t v : f.maps.flags) unsolved += (v & kLowSignal) != 0;
  EXPECT_EQ(zero, unsolved);
  // Every solved pixel but the one without a usable albedo has all three colours.
  EXPECT_EQ(solved_nonzero, f.w * f.h - unsolved - 1);
  // One column (red and green sites, no blue): a green site's red from the red sites above and below it.
  Field column = MakeField(1, 9, 1);
  internal::DemosaicAlbedo(Mosaic{}, column.own.data(), 1.5f, 1, &column.maps);
  EXPECT_FLOAT_EQ(column.maps.albedo.at(0, 3)[0], 0.5f * (column.own[2] + column.own[4]));
  EXPECT_EQ(column.maps.albedo.at(0, 3)[2], 0.f);
  // A mono sensor: the pixel's albedo in all three.
  internal::DemosaicAlbedo(Mosaic{.mono = true}, f.own.data(), 1.5f, 2, &f.maps);
  EXPECT_EQ(f.maps.albedo.at(3, 3)[0], f.own[static_cast<size_t>(3) * f.w + 3]);
  EXPECT_EQ(f.maps.albedo.at(3, 3)[2], f.own[static_cast<size_t>(3) * f.w + 3]);
}

}  // namespace
}  // namespace stage::processing

namespace stage::processing {
namespace {

// A pixel that solves to an albedo no surface has (a deep cavity: ~800 in a nostril) is flagged implausible and left
// out, and lends no colour to its neighbours: the colours they do not measure stay their own hue's.
TEST(DemosaicAlbedoTest, AnImplausibleAlbedoIsLeftOutAndLendsNoHue) {
  Field f = MakeField(24, 24, 100);  // one hue everywhere
  f.maps.confidence = Image(24, 24, 1);
  std::fill(f.maps.confidence.pixels.begin(), f.maps.confidence.pixels.end(), 0.9f);
  const size_t cavity = 12 * 24 + 12;
  f.own[cavity] = 800;
  internal::DemosaicAlbedo(Mosaic{}, f.own.data(), 1.5f, 2, &f.maps);
  EXPECT_EQ(f.maps.flags[cavity] & kImplausible, kImplausible);
  EXPECT_EQ(f.maps.confidence.pixels[cavity], 0.f);
  for (int c = 0; c < 3; ++c) EXPECT_EQ(f.maps.albedo.at(12, 12)[c], 0.f);
  // Its neighbours: every colour within the texture's range of the truth (the cavity's value would make it hundreds).
  for (int y = 10; y <= 14; ++y) {
    for (int x = 10; x <= 14; ++x) {
      if (x == 12 && y == 12) continue;
      EXPECT_EQ(f.maps.flags[static_cast<size_t>(y) * 24 + x] & kImplausible, 0) << x << "," << y;
      for (int c = 0; c < 3; ++c) {
        const float truth = f.truth[static_cast<size_t>(y) * 24 + x][c];
        EXPECT_NEAR(f.maps.albedo.at(x, y)[c] / truth, 1.0, 0.35) << x << "," << y << " channel " << c;
      }
    }
  }
}

TEST(DemosaicAlbedoTest, AnImplausibleRgbAlbedoIsLeftOut) {
  PhotometricMaps m;
  m.width = 3;
  m.height = 1;
  m.albedo = Image(3, 1, 3);
  m.confidence = Image(3, 1, 1);
  m.flags = {0, 0, kLowSignal};
  const float values[9] = {0.5f, 0.4f, 0.3f, 0.5f, 124.f, 0.3f, 0, 0, 0};
  std::copy(values, values + 9, m.albedo.pixels.begin());
  std::fill(m.confidence.pixels.begin(), m.confidence.pixels.end(), 0.8f);
  internal::FlagImplausibleRgbAlbedo(1.5f, &m);
  EXPECT_EQ(m.flags[0], 0);
  EXPECT_EQ(m.flags[1], kImplausible);
  EXPECT_EQ(m.flags[2], kLowSignal);
  EXPECT_EQ(m.albedo.at(1, 0)[1], 0.f);
  EXPECT_EQ(m.confidence.pixels[1], 0.f);
  EXPECT_EQ(m.albedo.at(0, 0)[0], 0.5f);
}

}  // namespace
}  // namespace stage::processing
