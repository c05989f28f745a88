// internal::PortableLog and PortableExp: accuracy against the C library in double, and the same bits in vector lanes
// as one value at a time. internal::LobeLimits: float thresholds that decide as the options' doubles do.
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <vector>

#include "gtest/gtest.h"
#include "photometric_internal.h"

namespace stage::processing {
namespace {

// |a - truth| in units of the float spacing at truth (the smaller of the spacings either side of the float nearest to
// it, so that a truth just below a power of two is not given the wider spacing above).
double UlpError(float a, double truth) {
  const float t = std::abs(static_cast<float>(truth));
  const double up = std::nextafter(t, std::numeric_limits<float>::infinity()) - static_cast<double>(t);
  const double down = static_cast<double>(t) - std::nextafter(t, 0.f);
  return std::abs(static_cast<double>(a) - truth) / std::min(up, down > 0 ? down : up);
}

std::vector<float> Sweep(float lo, float hi, int n, bool geometric) {
  std::vector<float> v(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) {
    const double f = static_cast<double>(i) / (n - 1);
    v[static_cast<size_t>(i)] = static_cast<float>(geometric ? lo * std::pow(static_cast<double>(hi) / lo, f)
                                                             : lo + (static_cast<double>(hi) - lo) * f);
  }
  return v;
}

TEST(PortableMathTest, LogIsWithinTwoUlpOfTheTrueValue) {
  double worst = 0;
  float at = 0;
  for (float x : Sweep(1e-37f, 1e37f, 200001, true)) {
    const double e = UlpError(internal::PortableLog(x), std::log(static_cast<double>(x)));
    if (e > worst) worst = e, at = x;
  }
  // Near 1, where the logarithm goes to 0, the spacing of its floats shrinks with it.
  for (float x : Sweep(0.5f, 2.f, 200001, false)) {
    const double e = UlpError(internal::PortableLog(x), std::log(static_cast<double>(x)));
    if (e > worst) worst = e, at = x;
  }
  std::printf("PortableLog: worst %.2f ulp at %g\n", worst, at);
  EXPECT_LE(worst, 2.0) << "at " << at;
  EXPECT_EQ(internal::PortableLog(1.f), 0.f);
  // Out of range: 0 and subnormals as the smallest normal float, infinity as the largest float.
  EXPECT_FLOAT_EQ(internal::PortableLog(0.f), std::log(std::numeric_limits<float>::min()));
  EXPECT_FLOAT_EQ(internal::PortableLog(1e-42f), std::log(std::numeric_limits<float>::min()));
  EXPECT_FLOAT_EQ(internal::PortableLog(std::numeric_limits<float>::infinity()),
                  std::log(std::numeric_limits<float>::max()));
}

TEST(PortableMathTest, ExpIsWithinTwoUlpOfTheTrueValue) {
  double worst = 0;
  float at = 0;
  for (float x : Sweep(-87.f, 88.f, 400001, false)) {
    const double e = UlpError(internal::PortableExp(x), std::exp(static_cast<double>(x)));
    if (e > worst) worst = e, at = x;
  }
  std::printf("PortableExp: worst %.2f ulp at %g\n", worst, at);
  EXPECT_LE(worst, 2.0) << "at " << at;
  EXPECT_EQ(internal::PortableExp(0.f), 1.f);
  EXPECT_FLOAT_EQ(internal::PortableExp(-1000.f), std::exp(-87.f));
  EXPECT_FLOAT_EQ(internal::PortableExp(1000.f), std::exp(88.f));
}

// The same functions over a row, vectorized for AVX-512 and for AVX2 with FMA (this file is compiled at -O3, as the
// library's row loops are, and without contraction), and one value at a time.
#if defined(__x86_64__)
__attribute__((target("arch=x86-64-v4"))) void RowV4(const float* in, int n, float* lg, float* ex) {
  for (int i = 0; i < n; ++i) {
    lg[i] = internal::PortableLog(in[i]);
    ex[i] = internal::PortableExp(in[i]);
  }
}

__attribute__((target("arch=x86-64-v3"))) void RowV3(const float* in, int n, float* lg, float* ex) {
  for (int i = 0; i < n; ++i) {
    lg[i] = internal::PortableLog(in[i]);
    ex[i] = internal::PortableExp(in[i]);
  }
}

#endif

__attribute__((optimize("no-tree-vectorize"))) void RowScalar(const float* in, int n, float* lg, float* ex) {
  for (int i = 0; i < n; ++i) {
    lg[i] = internal::PortableLog(in[i]);
    ex[i] = internal::PortableExp(in[i]);
  }
}

TEST(PortableMathTest, VectorLanesGiveTheBitsOfOneValueAtATime) {
  std::vector<float> in = Sweep(1e-6f, 80.f, 100003, true);
  for (float x : Sweep(-90.f, 90.f, 10007, false)) in.push_back(x);
  // And the edges: zero, a subnormal, the float range's ends, infinities, NaN.
  for (float x : {0.f, -0.f, 1e-42f, std::numeric_limits<float>::min(), std::numeric_limits<float>::max(),
                  std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
                  std::numeric_limits<float>::quiet_NaN()}) {
    in.push_back(x);
  }
  const int n = static_cast<int>(in.size());
  std::vector<float> lg_s(in.size()), ex_s(in.size());
  RowScalar(in.data(), n, lg_s.data(), ex_s.data());
  int checked = 0;
  auto check = [&](const char* name, void (*row)(const float*, int, float*, float*)) {
    std::vector<float> lg_v(in.size()), ex_v(in.size());
    row(in.data(), n, lg_v.data(), ex_v.data());
    EXPECT_EQ(std::memcmp(lg_v.data(), lg_s.data(), in.size() * sizeof(float)), 0) << name;
    EXPECT_EQ(std::memcmp(ex_v.data(), ex_s.data(), in.size() * sizeof(float)), 0) << name;
    ++checked;
  };
#if defined(__x86_64__)
  if (__builtin_cpu_supports("x86-64-v4")) check("x86-64-v4", RowV4);
  if (__builtin_cpu_supports("x86-64-v3")) check("x86-64-v3", RowV3);
#else
  (void)check;
#endif
  if (checked == 0) GTEST_SKIP() << "neither AVX2 nor AVX-512 on this CPU (or not an x86-64 target)";
}

// A float passes LobeLimits' float thresholds exactly when it passes the options' doubles (which the lobe's tests in
// float lanes stand in for): thresholds a float holds and ones it does not (0.1, 1/3: a plain cast rounds them up or
// down), beyond float's range and in its subnormals; the floats around each, and the infinities.
TEST(LobeLimitsTest, AFloatPassesTheFloatThresholdExactlyWhenItPassesTheDouble) {
  const float finf = std::numeric_limits<float>::infinity();
  int checked = 0;
  for (double d : {3.0, 15.0, 0.1, 1.0 / 3, 2.0 / 3, -2.5, 0.0, 1e-40, 1e39, -1e39, 7.000000000000001}) {
    PhotometricOptions options;
    options.min_specular_snr = d;
    options.max_specular_sigma_deg = d;
    const internal::LobeLimits limits(options);
    std::vector<float> xs = {-finf, finf};
    for (float x = std::nextafter(static_cast<float>(d), -finf), up = x, down = x; xs.size() < 82;) {
      xs.push_back(up);
      xs.push_back(down);
      up = std::nextafter(up, finf);
      down = std::nextafter(down, -finf);
    }
    for (float x : xs) {
      EXPECT_EQ(x >= d, x >= limits.min_snr) << "x " << x << ", least SNR " << d;
      EXPECT_EQ(x <= d, x <= limits.max_sigma_deg) << "x " << x << ", largest sigma " << d;
      ++checked;
    }
  }
  EXPECT_GT(checked, 800);
}

}  // namespace
}  // namespace stage::processing
