// Internals shared by the two ways photometric stereo runs (photometric.cc: per pixel, exact, with or without
// geometry; fast_photometric.cc: table-driven from the raw mosaic, without geometry). Not part of the library's API.
#pragma once

// The x86-64 kernels (AVX-512 chosen at run time, non-temporal stores) are built only for an x86-64 target; elsewhere
// (an arm64 light node's host) the portable twins beside them are the only path.
#if defined(__x86_64__)
#define STAGE_X86_64 1
#include <immintrin.h>
#else
#define STAGE_X86_64 0
#endif

#include <Eigen/Core>
#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "parallel.h"
#include "stage/processing/light_model.h"
#include "stage/processing/photometric.h"

// A hot loop over a row, compiled for AVX-512 and AVX2 as well as the baseline x86-64 (the best the CPU has is picked
// when the program starts).
#define STAGE_ROW_LOOP __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))

namespace stage::processing::internal {

constexpr float kPi = 3.14159265358979323846f;
constexpr int kMoments = 10;

// The natural logarithm and exponential of a float, from Cephes' logf and expf (within 2 ulp of the true values over
// the ranges below), in plain float arithmetic that the compiler turns into vector code across a row. Unlike the
// C library's, whose variant is picked at run time by what the CPU has (an FMA one or not), they give the same bits
// in any vector lane and on any x86-64 CPU, in files compiled without contraction (-ffp-contract=off), and cost a few
// instructions a lane rather than a call a value.
// log(x) for x > 0; values below the smallest normal float are taken as it (-87.34), +inf gives 88.72.
inline float PortableLog(float x) {
  x = std::min(std::max(x, std::numeric_limits<float>::min()), std::numeric_limits<float>::max());
  const uint32_t bits = std::bit_cast<uint32_t>(x);
  // x = m 2^e with m in [0.5, 1); then m in [sqrt(1/2), sqrt(2)) and f = m - 1.
  const float m = std::bit_cast<float>((bits & 0x007fffffu) | 0x3f000000u);
  // The choices select constants, not the results of arithmetic, so that they run in vector lanes (the compiler does
  // not do a floating-point operation on a path the code did not take).
  const bool low = m < 0.707106781186547524f;
  const float e = static_cast<float>(static_cast<int32_t>(bits >> 23) - 126) - (low ? 1.f : 0.f);
  const float f = m * (low ? 2.f : 1.f) - 1;
  const float z = f * f;
  float y = 7.0376836292e-2f;
  y = y * f - 1.1514610310e-1f;
  y = y * f + 1.1676998740e-1f;
  y = y * f - 1.2420140846e-1f;
  y = y * f + 1.4249322787e-1f;
  y = y * f - 1.6668057665e-1f;
  y = y * f + 2.0000714765e-1f;
  y = y * f - 2.4999993993e-1f;
  y = y * f + 3.3333331174e-1f;
  y = y * f * z;
  y += -2.12194440e-4f * e;
  y += -0.5f * z;
  return f + y + 0.693359375f * e;
}

// exp(x), x clamped to [-87, 88] (the floats' normal range).
inline float PortableExp(float x) {
  x = std::min(std::max(x, -87.f), 88.f);
  // n = round(x / ln 2) (adding 1.5 2^23 rounds to the nearest integer, which the sum's low bits then hold: no
  // float-to-int conversion, undefined for NaN), r = x - n ln 2 in two parts.
  constexpr float kRound = 12582912.f;
  const float t = x * 1.44269504088896341f + kRound;
  const float n = t - kRound;
  const float r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
  const float z = r * r;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * z + r + 1;
  const uint32_t ni = std::bit_cast<uint32_t>(t) - std::bit_cast<uint32_t>(kRound);  // n, modulo 2^32
  return p * std::bit_cast<float>((ni + 127u) << 23);
}

// The cross patterns and their parallel twins (the same gradient under either polarization), paired.
struct Twins {
  std::vector<int> cross, parallel;                          // the same gradient under either polarization, paired
  int full = -1;                                             // index into cross/parallel of the full-on pattern
  int xp = -1, xm = -1, yp = -1, ym = -1, zp = -1, zm = -1;  // first-order gradients (for the first guess)
};

absl::StatusOr<Twins> PairPatterns(const LightModel& light);

// Columns per tile of the fast solver's per-row work (SolvePhotometricFast): 512 by default. Results do not depend on
// it; tests set it small to check that.
int& FastTileColumns();

// Whether the fast solver's per-pixel steps, and the specular regularization's window sums (both solvers), run across
// AVX-512 lanes where the CPU has it (true by default). The results are the same bits either way; tests turn it off to
// check that.
bool& FastVectorKernels();
// Whether this CPU has what the vector kernels use (AVX-512 F and DQ).
bool FastVectorKernelsAvailable();

// Pattern weights unit-major (w[l * np + p]) for the paired patterns, and the coefficients that turn the specular
// images into the lobe's moments (sum_p c_p w_p(l) ~ f(l) over the units, by least squares).
struct PatternMatrix {
  int np = 0, units = 0;
  std::vector<float> cross, parallel;
  // Rows: the lobe's moments 1, x, y, z, xx, yy, zz, xy, yz, xz (sum over units of the function times the light).
  Eigen::Matrix<float, kMoments, Eigen::Dynamic> moments;
};

PatternMatrix MakePatternMatrix(const LightModel& light, const Twins& t);

// H_p(n) of every paired cross pattern as a point sees the units: sum over the units lit on n's side.
void DiffuseFromView(const UnitView& view, const PatternMatrix& pm, const Eigen::Vector3f& n, float* hp);

// The specular images a lobe with normal n, roughness alpha and rho_s = 1 gives under the paired parallel patterns,
// seen from v.
void SpecularFromView(const UnitView& view, const PatternMatrix& pm, const Eigen::Vector3f& n, const Eigen::Vector3f& v,
                      float alpha, float* m);

// The working memory the solvers share (PhotometricMaps::work), per pixel: the specular fit's noise of the normal's
// direction (rad^2, both axes) and of log roughness (the regularization's weights), and each pixel's albedo in the
// colour it measures (DemosaicAlbedo's input). Sized and returned by Work().
enum WorkSlot { kVarNormal = 0, kVarLogAlpha = 1, kOwnAlbedo = 2, kSlots = 3 };
float* Work(PhotometricMaps* m, WorkSlot slot);

// The variance (DN^2) that reading adds to a pixel's three channels summed: read noise and quantization (1/12 DN^2 a
// channel, so that a camera calibrated with no read noise still weights a dark pixel finitely).
inline float ReadVarianceDn2(const PhotometricCamera& camera) {
  const double read = camera.read_noise_e / camera.gain_e_per_dn;
  return static_cast<float>(3 * (read * read + 1.0 / 12));
}

// The least full-on level (DN, channels summed) a pixel is solved at: min_signal_dn, and min_signal_sigma standard
// deviations of the sum's read noise.
inline double MinSignalDn(const PhotometricOptions& options, const PhotometricCamera& camera) {
  return std::max(options.min_signal_dn, options.min_signal_sigma * std::sqrt(double{ReadVarianceDn2(camera)}));
}

// Whether a fitted lobe counts as measured (PhotometricOptions): bright enough, its normal, intensity and log
// roughness known well enough, and wider than 2 * kMinLobeAlpha (a narrower one only says "one unit").
constexpr float kMinLobeAlpha = 0.02f;
// The least float not below v, and the greatest not above it: a float x passes x >= v (x <= v) exactly when it
// passes the comparison with that float, so that a double threshold can be tested in float.
inline float FloatAtLeast(double v) {
  const float f = static_cast<float>(v);
  return f < v ? std::nextafter(f, HUGE_VALF) : f;
}
inline float FloatAtMost(double v) {
  const float f = static_cast<float>(v);
  return f > v ? std::nextafter(f, -HUGE_VALF) : f;
}

// The options' two thresholds (doubles) as floats that a float passes exactly when it passes the double, so that the
// tests run in float (and in the fast solver's vector lanes).
struct LobeLimits {
  explicit LobeLimits(const PhotometricOptions& options)
      : min_snr(FloatAtLeast(options.min_specular_snr)), max_sigma_deg(FloatAtMost(options.max_specular_sigma_deg)) {}
  float min_snr;
  float max_sigma_deg;
};
inline bool LobeMeasured(const LobeLimits& limits, float spec_snr, float var_n, float rho, float var_rho,
                         float var_log_alpha, float alpha) {
  // & rather than &&: every test computed, no branch (the fast solver's lookup runs it in vector lanes).
  return (rho > 0) & (spec_snr >= limits.min_snr) & (std::sqrt(var_n) * 180 / kPi <= limits.max_sigma_deg) &
         (std::sqrt(var_rho) <= 0.5f * rho) & (var_log_alpha <= 0.25f) & (alpha > 2 * kMinLobeAlpha);
}

// A pixel's confidence: its full-on's SNR (cross only, channels summed; 1 at 100) times the diffuse fit's agreement
// (reduced chi-square), 0 when clipped, halved in shadow.
inline float Confidence(float full_on, float gain_e_per_dn, float read_dn2, float chi2, uint8_t flags) {
  const float snr = full_on / std::sqrt(std::max(0.f, full_on) / gain_e_per_dn + read_dn2);
  float conf = std::min(1.f, std::max(0.f, snr) / 100.f) * PortableExp(-std::max(0.f, chi2 - 2.f) / 4.f);
  if (flags & kSaturated) conf = 0;
  if (flags & kShadowed) conf *= 0.5f;
  return conf;
}

// The pixels a row's background is zeroed in at a time (a multiple of 16: 3 floats a pixel then fill whole lines).
constexpr int kStreamRun = 256;

// Zeros n floats from p with non-temporal stores (the middle, 16-byte aligned; plain stores at the ends): for memory
// nothing reads again soon (the background's maps), so that the lines are not first read from memory and do not
// push the working set out of the caches. The stores are weakly ordered: the thread calls StreamFence() before others
// read them. Plain stores where the target has no x86 non-temporal stores.
inline void StreamZeros(float* p, size_t n) {
  while (n > 0 && (reinterpret_cast<uintptr_t>(p) & 15) != 0) {
    *p++ = 0;
    --n;
  }
#if STAGE_X86_64
  const __m128 zero = _mm_setzero_ps();
  for (; n >= 4; n -= 4, p += 4) _mm_stream_ps(p, zero);
#endif
  while (n > 0) {
    *p++ = 0;
    --n;
  }
}

// Orders the non-temporal stores before later ones (x86 sfence; nothing to do for plain stores).
inline void StreamFence() {
#if STAGE_X86_64
  _mm_sfence();
#endif
}

// Copies n floats from src to dst with non-temporal stores, as StreamZeros.
inline void StreamCopy(float* dst, const float* src, size_t n) {
  while (n > 0 && (reinterpret_cast<uintptr_t>(dst) & 15) != 0) {
    *dst++ = *src++;
    --n;
  }
#if STAGE_X86_64
  for (; n >= 4; n -= 4, dst += 4, src += 4) _mm_stream_ps(dst, _mm_loadu_ps(src));
#endif
  while (n > 0) {
    *dst++ = *src++;
    --n;
  }
}

// Sizes every map of `m` for width x height (keeping their memory when the size is the same; contents are not
// cleared: the solver writes every pixel).
void PrepareMaps(int width, int height, PhotometricMaps* m);

// Writes the RGB albedo map (m->albedo) from each solved pixel's albedo in the colour it measures (own, one float a
// pixel; m->flags says which are solved): that colour as it is, and each of the other two as the pixel's albedo times
// the local hue, exp of the mean over a 5 x 5 window of each site's log(colour / measured colour), its missing colours
// the geometric mean of its neighbours of that colour. Of the window centred on the pixel and the four 2 pixels off
// it (left, right, above, below), the one whose hue varies least, so that a window straddling a change of hue (lips,
// brows) is passed over. Where no window has 3 usable sites: the mean of the solved neighbours of each colour (0 for
// none). 0 where nothing is solved. A mono mosaic: the pixel's albedo in all three. A solved pixel whose own albedo is
// above `max_albedo` (or not finite) is flagged kImplausible first (confidence 0): it is then not solved for the map,
// and lends its neighbours nothing.
void DemosaicAlbedo(const Mosaic& mosaic, const float* own, float max_albedo, int threads, PhotometricMaps* m);

// The per-pixel solver's RGB images (no mosaic): a solved pixel with a channel above `max_albedo` (or not finite) is
// flagged kImplausible, its albedo zeroed and its confidence 0.
void FlagImplausibleRgbAlbedo(float max_albedo, PhotometricMaps* m);

// Regularizes the specular maps in place: the departure of the raw specular normal from the diffuse normal, and log
// roughness, filtered by a local Wiener filter over `radius` among neighbours on the same side of an edge (diffuse
// normals within 30 degrees), each pixel's noise from the work slots. Writes the regularized specular normals (stage
// and camera frames) and roughness of every pixel with a lobe; zero specular normals elsewhere (the roughness of
// those is the caller's: zero).
void RegularizeSpecular(int radius, int threads, const Eigen::Matrix3f& to_camera, PhotometricMaps* m);

}  // namespace stage::processing::internal
