// Table-driven photometric stereo from the raw mosaic: see fast_photometric.h.
#include "stage/processing/fast_photometric.h"

#include <sys/mman.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <mutex>

// GCC 12 warns of the AVX-512 intrinsics' own undefined source operands (_mm512_undefined_*) where they are inlined.
#if defined(__x86_64__)  // photometric_internal.h's STAGE_X86_64; first, so that the pragmas cover the intrinsics
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wuninitialized"
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <immintrin.h>
#pragma GCC diagnostic pop
#endif

#include "absl/strings/str_cat.h"
#include "photometric_internal.h"

namespace stage::processing {

using internal::kPi;

namespace {

// A table's floats in memory that the kernel may back with 2 MiB pages (transparent huge pages, where the system
// enables them on request): the per-pixel lookups land all over the tables, and with 4 KiB pages nearly every one of
// them missed the TLB.
class HugeArray {
 public:
  HugeArray() = default;
  HugeArray(const HugeArray&) = delete;
  HugeArray& operator=(const HugeArray&) = delete;
  ~HugeArray() { Release(); }

  void assign(size_t n, float value) {
    Release();
    n_ = n;
    if (n == 0) return;
    constexpr size_t kHuge = size_t{2} << 20;
    const size_t bytes = (n * sizeof(float) + kHuge - 1) / kHuge * kHuge;
    mapped_bytes_ = bytes + kHuge;  // room to start on a 2 MiB boundary
    mapped_ = mmap(nullptr, mapped_bytes_, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (mapped_ == MAP_FAILED) throw std::bad_alloc();
    const auto start = (reinterpret_cast<uintptr_t>(mapped_) + kHuge - 1) / kHuge * kHuge;
    p_ = reinterpret_cast<float*>(start);
    madvise(p_, bytes, MADV_HUGEPAGE);  // a request: without it, ordinary pages
    std::fill_n(p_, n, value);
  }
  void resize(size_t n) { assign(n, 0.f); }
  size_t size() const { return n_; }
  float* data() { return p_; }
  const float* data() const { return p_; }
  float& operator[](size_t i) { return p_[i]; }
  const float& operator[](size_t i) const { return p_[i]; }

 private:
  void Release() {
    if (mapped_ != nullptr) munmap(mapped_, mapped_bytes_);
    mapped_ = nullptr;
    p_ = nullptr;
    n_ = 0;
  }
  void* mapped_ = nullptr;
  size_t mapped_bytes_ = 0;
  float* p_ = nullptr;
  size_t n_ = 0;
};

}  // namespace

struct PhotometricTables::Data {
  internal::Twins twins;
  internal::PatternMatrix pm;
  int np = 0;
  int patterns = 0;  // of the light model the tables were built for
  // Diffuse, n x n octahedral cells of the normal: per cell H (np x 3), M (3 x np, row-major), and sum_p H_p (3).
  int n = 0;
  HugeArray h, m, hsum;
  // Specular, s x s octahedral cells of the lobe's measured mean direction, j roughness samples; per (cell, sample):
  // the step to the true mirror direction (3), the lobe's angular variance about its mean direction, its total
  // (moment 0), and its image under every pattern (np), per unit of rho_s and spec_scale. A total of 0: the lobe falls
  // off the dome there.
  int s = 0, j = 0;
  std::vector<float> log_alpha;
  HugeArray spec;
  int spec_stride = 0;
  // Per cell: the run of roughness samples the lookup uses (the first with a lobe, and the last of the run of samples
  // with one after it; -1: none), and the samples' spreads (spec's entry 3) side by side, so that finding the roughness
  // reads one cache line, not one per sample.
  std::vector<int32_t> first, last;
  std::vector<float> spread;
  Eigen::Vector3f view = Eigen::Vector3f::UnitZ();  // the camera's central view (towards it from the stage origin)

  int Cell(const Eigen::Vector3f& dir, int size) const {
    const Eigen::Vector2f uv = OctEncode(dir);
    const int u = std::clamp(static_cast<int>(uv.x() * static_cast<float>(size)), 0, size - 1);
    const int v = std::clamp(static_cast<int>(uv.y() * static_cast<float>(size)), 0, size - 1);
    return v * size + u;
  }
};

PhotometricTables::~PhotometricTables() = default;

bool& internal::FastVectorKernels() {
  static bool use = true;
  return use;
}

bool internal::FastVectorKernelsAvailable() {
#if STAGE_X86_64
  static const bool has = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq");
  return has;
#else
  return false;  // the portable kernels only (chosen at build time: not an x86-64 target)
#endif
}

int& internal::FastTileColumns() {
  static int columns = 512;
  return columns;
}

namespace {

constexpr int kDiffuseCells = 128;
constexpr int kSpecularCells = 48;
constexpr int kAlphas = 12;
constexpr float kAlphaMin = 0.04f, kAlphaMax = 1.0f;
// A lobe's mean direction must land within 0.02 rad of the cell it is tabled for: the cosine of that (a constant, not a
// library call whose last bit may depend on the CPU).
constexpr float kCosReach = 0.99980000666657776f;

// The lobe from its moments mu (1, x, y, z, xx, yy, zz, xy, yz, xz): its mean direction and the angular variance
// about it (1 - r^T M2 r with M2 the normalized second moments: the lobe's spread, which roughness sets). Computed
// without a branch (the fields are computed where !ok too, and mean nothing there), for the lookup's loop over its
// lanes (which GCC 12 makes vector code of); the table is built with it as well.
struct LobeMoments {
  float mu0 = 0;
  float mean[3] = {0, 0, 0};  // unit
  float length = 0;           // of the first moment, before normalizing: mu0 times R < 1
  float spread = 0;
  bool ok = false;  // a lobe: mu0 > 0 and a first moment
};

// mu(r): the r-th moment (an array, or one lane of the lanes' moments: see LookUpLobesImpl).
template <typename Moment>
inline LobeMoments FromMoments(Moment mu) {
  LobeMoments out;
  const float x = mu(1), y = mu(2), z = mu(3);
  const float n = std::sqrt(x * x + (y * y + z * z));  // as Eigen's norm()
  out.mu0 = mu(0);
  out.ok = (mu(0) > 0) & !(n < 1e-6f * mu(0));  // & rather than &&: no branch in the lanes' loop
  out.length = n;
  const float rx = x / n, ry = y / n, rz = z / n;
  out.mean[0] = rx;
  out.mean[1] = ry;
  out.mean[2] = rz;
  // r^T M2 r with M2 = [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]] / mu0.
  const float q =
      rx * rx * mu(4) + ry * ry * mu(5) + rz * rz * mu(6) + 2 * (rx * ry * mu(7) + ry * rz * mu(8) + rx * rz * mu(9));
  out.spread = 1 - q / mu(0);
  return out;
}

LobeMoments Moments(const internal::PatternMatrix& pm, const float* s) {
  float mu[internal::kMoments];
  for (int r = 0; r < internal::kMoments; ++r) {
    float sum = 0;
    for (int k = 0; k < pm.np; ++k) sum += pm.moments(r, k) * s[k];
    mu[r] = sum;
  }
  return FromMoments([&](int r) { return mu[r]; });
}

// GCC's vector extension: 16 floats, lowered to what each function's target has (one AVX-512 register, two AVX2, four
// SSE).
typedef float V16 __attribute__((vector_size(64)));

// Loads 16 floats (a macro, not a function: a function returning a vector of 64 bytes has a different ABI with and
// without AVX-512).
#define STAGE_LOAD16(v, p) std::memcpy(&(v), (p), sizeof(V16))

// Floats after the specular table's last entry, so that the lookup may read 16 at a time past it.
constexpr size_t kSpecPad = 32;

// A raw row less the black level, divided by the flat field (null: none).
STAGE_ROW_LOOP void CorrectRow(const uint16_t* __restrict raw, const float* __restrict flat, float black, int w,
                               float* __restrict out) {
  if (flat != nullptr) {
    for (int x = 0; x < w; ++x) out[x] = (static_cast<float>(raw[x]) - black) / flat[x];
  } else {
    for (int x = 0; x < w; ++x) out[x] = static_cast<float>(raw[x]) - black;
  }
}

// The channel sum of a bilinear demosaic along a row: own value times `self`, plus kc times the 4 edge neighbours and
// kd times the 4 diagonal ones (per pixel: its Bayer site's weights). The rows hold a column of halo either side
// (index -1 and w).
STAGE_ROW_LOOP void ChannelSumRow(const float* __restrict up, const float* __restrict mid, const float* __restrict down,
                                  const float* __restrict kc, const float* __restrict kd, float self, int w,
                                  float* __restrict out) {
  for (int x = 0; x < w; ++x) {
    out[x] = self * mid[x] + kc[x] * (mid[x - 1] + mid[x + 1] + up[x] + down[x]) +
             kd[x] * (up[x - 1] + up[x + 1] + down[x - 1] + down[x + 1]);
  }
}

// A pattern pair's three rows (above, at and below the row) of the cross image and of the parallel one.
struct PairRows {
  const float* cross[3];
  const float* parallel[3];
};

// Per pattern pair along a row, from the channel sums (ChannelSumRow's, in registers) of its cross (dc) and parallel
// (dp) images: the diffuse in the cross image (the leaked specular taken away), the specular (parallel - cross, for
// the leak), the specular's variance (shot and read noise of both images) and its inverse, the diffuse's inverse
// variance, and the mean of both images. (The channel sums of every pattern written out and read back per pair cost
// 10 ms more on the benchmark.)
STAGE_ROW_LOOP void ChannelSumPairRow(const PairRows& rows, const float* __restrict kc, const float* __restrict kd,
                                      float self, float k_leak, float spec_gain, float inv_g, float read, int w,
                                      float* __restrict d, float* __restrict s, float* __restrict sv,
                                      float* __restrict sw, float* __restrict dw, float* __restrict ds) {
  const float* __restrict cu = rows.cross[0];
  const float* __restrict cm = rows.cross[1];
  const float* __restrict cd = rows.cross[2];
  const float* __restrict pu = rows.parallel[0];
  const float* __restrict pm = rows.parallel[1];
  const float* __restrict pd = rows.parallel[2];
  const float gain2 = spec_gain * spec_gain;
  for (int x = 0; x < w; ++x) {
    // ChannelSumRow's expression, written out: the probe's channel sums must be the same bits. (One inline function
    // for both lost the pointers' __restrict where it was inlined, and GCC 12 then kept the AVX-512 clone scalar:
    // 365 -> 490 ms.)
    const float dc = self * cm[x] + kc[x] * (cm[x - 1] + cm[x + 1] + cu[x] + cd[x]) +
                     kd[x] * (cu[x - 1] + cu[x + 1] + cd[x - 1] + cd[x + 1]);
    const float dp = self * pm[x] + kc[x] * (pm[x - 1] + pm[x + 1] + pu[x] + pd[x]) +
                     kd[x] * (pu[x - 1] + pu[x + 1] + pd[x - 1] + pd[x + 1]);
    const float diffuse = dc - k_leak * (dp - dc);
    d[x] = diffuse;
    s[x] = (dp - dc) * spec_gain;
    sv[x] = gain2 * (std::max(0.f, dp + dc) * inv_g + 2 * read);
    sw[x] = 1.f / sv[x];
    dw[x] = 1.f / (std::max(0.f, diffuse) * inv_g + read);
    ds[x] = 0.5f * (dc + dp);
  }
}

// The lobe's moments along a row (kMoments rows `stride` apart) from the specular rows s (np rows), and the first
// moment's variance v1 from the specular variance rows sv: 16 columns at a time, their sums kept in registers over
// the pattern pairs. Columns are computed up to w rounded up to 16 (the rows have room).
STAGE_ROW_LOOP void MomentRows(const float* __restrict s, const float* __restrict sv, size_t stride, int np,
                               const float* __restrict coef, const float* __restrict q1, int w, float* __restrict mu,
                               float* __restrict v1) {
  for (int x0 = 0; x0 < w; x0 += 16) {
    V16 acc[internal::kMoments] = {};
    V16 var = {};
    for (int k = 0; k < np; ++k) {
      V16 src, vsrc;
      std::memcpy(&src, s + static_cast<size_t>(k) * stride + x0, sizeof src);
      std::memcpy(&vsrc, sv + static_cast<size_t>(k) * stride + x0, sizeof vsrc);
      for (int r = 0; r < internal::kMoments; ++r) acc[r] += coef[k * internal::kMoments + r] * src;
      var += q1[k] * vsrc;
    }
    for (int r = 0; r < internal::kMoments; ++r)
      std::memcpy(mu + static_cast<size_t>(r) * stride + x0, &acc[r], sizeof(V16));
    std::memcpy(v1 + x0, &var, sizeof var);
  }
}

// A pixel's own value summed over the pattern pairs: the cross image less its leaked specular (own_cross), and the
// mean of both images (own_both; the lobe is taken away per pixel).
STAGE_ROW_LOOP void OwnRow(const float* __restrict oc, const float* __restrict op, float k_leak, int w,
                           float* __restrict own_cross, float* __restrict own_both) {
  for (int x = 0; x < w; ++x) {
    own_cross[x] += oc[x] - k_leak * (op[x] - oc[x]);
    own_both[x] += 0.5f * (oc[x] + op[x]);
  }
}

// Marks the pixels of a row whose raw value is clipped (the sensor's top level), before any correction.
STAGE_ROW_LOOP void SaturationRow(const uint16_t* __restrict raw, uint16_t top, int w, uint8_t* __restrict saturated) {
  for (int x = 0; x < w; ++x) saturated[x] |= raw[x] >= top ? 1 : 0;
}

// The per-pixel steps take a row's pixels kLanes at a time: the diffuse solves run across them in vector lanes (below),
// and so does the lobe's lookup, but for the interpolation of each pixel's table entry.
constexpr int kLanes = 16;

// What the diffuse steps read, for a row of a tile: the per-pair rows (np rows `stride` apart, from the tile's column
// 0) and the constants.
struct DiffuseRow {
  const PhotometricTables::Data* t = nullptr;
  const float* rd = nullptr;   // the diffuse in the cross image
  const float* rds = nullptr;  // the mean of both polarizations
  const float* rdw = nullptr;  // the diffuse's inverse variance
  const float* own_cross = nullptr;
  const float* own_both = nullptr;
  size_t stride = 0;
  float ws = 1;          // the white scale
  float half_leak = 0;   // 0.5 (1 + leak): the lobe's share of the mean of both polarizations
  float min_signal = 0;  // the least signal to solve (the full-on pair's diffuse), DN
  int full = 0;
  bool guess = false;  // the six first-order gradients are there for a first guess
  int xp = 0, xm = 0, yp = 0, ym = 0, zp = 0, zm = 0;
  Eigen::Vector3f toward = Eigen::Vector3f::UnitZ();
};

// Up to kLanes pixels of a row through the per-pixel steps (lane l: column xb + l of the tile).
// The flags are bytes (0 or 1), not bool: GCC 12 does not vectorize loops that load bool.
struct Batch {
  float n[3][kLanes];        // the diffuse normal: from the first solves, then the last
  float u[3][kLanes];        // the first solves' vector (albedo times normal), for the last steps
  uint8_t solved[kLanes];    // the first solves gave a normal (else: too little signal)
  uint8_t both[kLanes];      // the lobe is known and fits: both polarizations hold the diffuse
  float lobe_sum[kLanes];    // the lobe's images summed over the pairs
  float chi2[kLanes];        // the diffuse fit's residual per degree of freedom
  float own_albedo[kLanes];  // the albedo of the colour the pixel measures
  // The specular, where the lobe is measured: its normal (before regularization), intensity, roughness, the normal's
  // noise in degrees, and the variances of the normal and of log roughness; a bad fit of the lobe to the images.
  uint8_t measured[kLanes];
  uint8_t spec_bad_fit[kLanes];
  float ns[3][kLanes];
  float rho[kLanes], alpha[kLanes], sigma_deg[kLanes], var_n[kLanes], var_log_alpha[kLanes];
};

// u = M(cell of `at`) data / white scale, data[k * step] the pair k's value.
Eigen::Vector3f SolveAt(const DiffuseRow& a, const float* data, size_t step, const Eigen::Vector3f& at) {
  const PhotometricTables::Data& t = *a.t;
  const float* mm = &t.m[static_cast<size_t>(t.Cell(at, t.n)) * 3 * t.np];
  Eigen::Vector3f u = Eigen::Vector3f::Zero();
  for (int k = 0; k < t.np; ++k) {
    const float dk = data[static_cast<size_t>(k) * step];
    u.x() += mm[k] * dk;
    u.y() += mm[t.np + k] * dk;
    u.z() += mm[2 * t.np + k] * dk;
  }
  return Eigen::Vector3f(u / a.ws);
}

// The diffuse's first solves, one pixel at a time: where there is signal, a first guess from the gradients, then
// u = M(n) d twice.
void DiffuseFirst(const DiffuseRow& a, int xb, int lanes, Batch* b) {
  for (int l = 0; l < lanes; ++l) {
    const float* d = a.rd + xb + l;
    b->solved[l] = false;
    if (d[static_cast<size_t>(a.full) * a.stride] < a.min_signal) continue;
    auto at = [&](int k) { return d[static_cast<size_t>(k) * a.stride]; };
    Eigen::Vector3f n = a.toward;
    if (a.guess) {
      const Eigen::Vector3f guess(at(a.xp) - at(a.xm), at(a.yp) - at(a.ym), at(a.zp) - at(a.zm));
      if (guess.norm() > 1e-6f) n = guess.normalized();
    }
    bool solved = true;
    Eigen::Vector3f u = n;
    for (int it = 0; it < 2 && solved; ++it) {
      u = SolveAt(a, d, a.stride, n);
      solved = u.allFinite() && u.norm() > 1e-9f;
      if (solved) n = u.normalized();
    }
    b->solved[l] = solved;
    for (int c = 0; c < 3; ++c) {
      b->n[c][l] = n[c];
      b->u[c][l] = u[c];
    }
  }
}

// The diffuse's last steps, one pixel at a time, for the solved pixels: with the lobe known (lobe: its image per pair,
// lobe[k * kLanes + l]), solved again from the mean of both polarizations less the lobe's share; the fit's residual;
// the albedo of the pixel's own colour (its images summed over the pairs, less the lobe's share, against the light
// summed the same way). d2: scratch of np * kLanes.
void DiffuseLast(const DiffuseRow& a, int xb, int lanes, const float* lobe, float* d2, Batch* b) {
  const PhotometricTables::Data& t = *a.t;
  const int np = t.np;
  for (int l = 0; l < lanes; ++l) {
    if (!b->solved[l]) continue;
    const int xt = xb + l;
    Eigen::Vector3f n(b->n[0][l], b->n[1][l], b->n[2][l]), u(b->u[0][l], b->u[1][l], b->u[2][l]);
    const bool both = b->both[l];
    for (int k = 0; k < np; ++k) {
      const size_t o = static_cast<size_t>(k) * a.stride + xt;
      d2[k] = both ? a.rds[o] - a.half_leak * lobe[k * kLanes + l] : a.rd[o];
    }
    if (both) {
      const Eigen::Vector3f u2 = SolveAt(a, d2, 1, n);
      if (u2.allFinite() && u2.norm() > 1e-9f) {
        u = u2;
        n = u.normalized();
      }
    }
    const size_t cell = static_cast<size_t>(t.Cell(n, t.n));
    const float* hh = &t.h[cell * 3 * np];
    float chi2 = 0;
    const float copies = both ? 2.f : 1.f;
    for (int k = 0; k < np; ++k) {
      const float pred = a.ws * (u.x() * hh[3 * k] + u.y() * hh[3 * k + 1] + u.z() * hh[3 * k + 2]);
      const float e = d2[k] - pred;
      chi2 += e * e * copies * a.rdw[static_cast<size_t>(k) * a.stride + xt];  // the variance at the measured level
    }
    b->chi2[l] = chi2 / static_cast<float>(std::max(1, np - 3));
    const float own = both ? a.own_both[xt] - a.half_leak * b->lobe_sum[l] / 3 : a.own_cross[xt];
    const Eigen::Vector3f hs(t.hsum[cell * 3], t.hsum[cell * 3 + 1], t.hsum[cell * 3 + 2]);
    const float shade = a.ws * n.dot(hs);
    b->own_albedo[l] = shade > 0 ? own / shade : 0.f;
    for (int c = 0; c < 3; ++c) b->n[c][l] = n[c];
  }
}

#if STAGE_X86_64
// The same two steps across the lanes of an AVX-512 register, on CPUs that have it. The same operations in the same
// order as above (a multiply and an add never fused: see processing/CMakeLists.txt), so the same bits; the tables'
// entries are gathered per lane.
#define STAGE_AVX512 __attribute__((target("avx512f,avx512dq")))

struct V3 {
  __m512 x, y, z;
};

// The octahedral cell of each lane's direction, as PhotometricTables::Data::Cell and OctEncode compute it.
STAGE_AVX512 inline __m512i Cells16(const V3& d, int size) {
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f), half = _mm512_set1_ps(0.5f);
  const __m512 s = _mm512_add_ps(_mm512_add_ps(_mm512_abs_ps(d.x), _mm512_abs_ps(d.y)), _mm512_abs_ps(d.z));
  __m512 x = _mm512_div_ps(d.x, s), y = _mm512_div_ps(d.y, s);
  const __mmask16 below = _mm512_cmp_ps_mask(d.z, zero, _CMP_LT_OQ);
  const __m512 sx = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(x, zero, _CMP_GE_OQ), _mm512_set1_ps(-1.f), one);
  const __m512 sy = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(y, zero, _CMP_GE_OQ), _mm512_set1_ps(-1.f), one);
  const __m512 ox = _mm512_mul_ps(_mm512_sub_ps(one, _mm512_abs_ps(y)), sx);
  const __m512 oy = _mm512_mul_ps(_mm512_sub_ps(one, _mm512_abs_ps(x)), sy);
  x = _mm512_mask_blend_ps(below, x, ox);
  y = _mm512_mask_blend_ps(below, y, oy);
  const __m512 fs = _mm512_set1_ps(static_cast<float>(size));
  const __m512 u = _mm512_mul_ps(_mm512_add_ps(_mm512_mul_ps(x, half), half), fs);
  const __m512 v = _mm512_mul_ps(_mm512_add_ps(_mm512_mul_ps(y, half), half), fs);
  const __m512i lo = _mm512_setzero_si512(), hi = _mm512_set1_epi32(size - 1);
  const __m512i iu = _mm512_min_epi32(_mm512_max_epi32(_mm512_cvttps_epi32(u), lo), hi);
  const __m512i iv = _mm512_min_epi32(_mm512_max_epi32(_mm512_cvttps_epi32(v), lo), hi);
  return _mm512_add_epi32(_mm512_mullo_epi32(iv, _mm512_set1_epi32(size)), iu);
}

// x a + (y b + z c): Eigen's order for a 3-vector's dot product (and squared norm).
STAGE_AVX512 inline __m512 Dot16(const V3& u, __m512 a, __m512 b, __m512 c) {
  return _mm512_add_ps(_mm512_mul_ps(u.x, a), _mm512_add_ps(_mm512_mul_ps(u.y, b), _mm512_mul_ps(u.z, c)));
}

STAGE_AVX512 inline __m512 Norm16(const V3& u) { return _mm512_sqrt_ps(Dot16(u, u.x, u.y, u.z)); }

// Lanes whose three components are finite and whose length exceeds `least`; the length in `norm`.
STAGE_AVX512 inline __mmask16 Usable16(const V3& u, float least, __m512* norm) {
  *norm = Norm16(u);
  const __mmask16 bad = _mm512_fpclass_ps_mask(u.x, 0x99) | _mm512_fpclass_ps_mask(u.y, 0x99) |
                        _mm512_fpclass_ps_mask(u.z, 0x99);  // NaN or infinite
  return static_cast<__mmask16>(~bad) & _mm512_cmp_ps_mask(*norm, _mm512_set1_ps(least), _CMP_GT_OQ);
}

STAGE_AVX512 inline V3 Divide16(const V3& u, __m512 by) {
  return {_mm512_div_ps(u.x, by), _mm512_div_ps(u.y, by), _mm512_div_ps(u.z, by)};
}

STAGE_AVX512 inline V3 Blend16(__mmask16 take, const V3& keep, const V3& other) {
  return {_mm512_mask_blend_ps(take, keep.x, other.x), _mm512_mask_blend_ps(take, keep.y, other.y),
          _mm512_mask_blend_ps(take, keep.z, other.z)};
}

// Per lane, the floats at table[i] and table[i + 1] (i in floats), gathered as pairs (8 + 8 of 64 bits): half the
// loads of two gathers of 16.
STAGE_AVX512 inline void GatherPair16(const float* table, __m512i i, __m512* first, __m512* second) {
  const __m512 lo = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_castsi512_si256(i), table, 4));
  const __m512 hi = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_extracti64x4_epi64(i, 1), table, 4));
  const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
  *first = _mm512_permutex2var_ps(lo, even, hi);
  *second = _mm512_permutex2var_ps(lo, _mm512_add_epi32(even, _mm512_set1_epi32(1)), hi);
}

// SolveAt across the lanes: data + k * step holds pair k's values of the 16 lanes. Two pairs at a time (their entries
// side by side in each row of M), summed in SolveAt's order.
STAGE_AVX512 inline V3 Solve16(const DiffuseRow& a, const float* data, size_t step, const V3& at) {
  const PhotometricTables::Data& t = *a.t;
  const int np = t.np;
  const __m512i base = _mm512_mullo_epi32(Cells16(at, t.n), _mm512_set1_epi32(3 * np));
  V3 u{_mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps()};
  const float* m = t.m.data();
  int k = 0;
  for (; k + 1 < np; k += 2) {
    const __m512 d0 = _mm512_loadu_ps(data + static_cast<size_t>(k) * step);
    const __m512 d1 = _mm512_loadu_ps(data + static_cast<size_t>(k + 1) * step);
    const __m512i i = _mm512_add_epi32(base, _mm512_set1_epi32(k));
    __m512 x0, x1, y0, y1, z0, z1;
    GatherPair16(m, i, &x0, &x1);
    GatherPair16(m, _mm512_add_epi32(i, _mm512_set1_epi32(np)), &y0, &y1);
    GatherPair16(m, _mm512_add_epi32(i, _mm512_set1_epi32(2 * np)), &z0, &z1);
    u.x = _mm512_add_ps(_mm512_add_ps(u.x, _mm512_mul_ps(x0, d0)), _mm512_mul_ps(x1, d1));
    u.y = _mm512_add_ps(_mm512_add_ps(u.y, _mm512_mul_ps(y0, d0)), _mm512_mul_ps(y1, d1));
    u.z = _mm512_add_ps(_mm512_add_ps(u.z, _mm512_mul_ps(z0, d0)), _mm512_mul_ps(z1, d1));
  }
  for (; k < np; ++k) {
    const __m512 dk = _mm512_loadu_ps(data + static_cast<size_t>(k) * step);
    const __m512i i = _mm512_add_epi32(base, _mm512_set1_epi32(k));
    u.x = _mm512_add_ps(u.x, _mm512_mul_ps(_mm512_i32gather_ps(i, m, 4), dk));
    u.y = _mm512_add_ps(u.y, _mm512_mul_ps(_mm512_i32gather_ps(_mm512_add_epi32(i, _mm512_set1_epi32(np)), m, 4), dk));
    u.z = _mm512_add_ps(u.z,
                        _mm512_mul_ps(_mm512_i32gather_ps(_mm512_add_epi32(i, _mm512_set1_epi32(2 * np)), m, 4), dk));
  }
  return Divide16(u, _mm512_set1_ps(a.ws));
}

// The 16 lanes of pair k's row.
STAGE_AVX512 inline __m512 Row16(const float* rows, size_t stride, int k) {
  return _mm512_loadu_ps(rows + static_cast<size_t>(k) * stride);
}

STAGE_AVX512 void DiffuseFirst16(const DiffuseRow& a, int xb, int lanes, Batch* b) {
  const __mmask16 live = static_cast<__mmask16>((1u << lanes) - 1);
  const float* d = a.rd + xb;
  const __mmask16 signal = static_cast<__mmask16>(
      live & ~_mm512_cmp_ps_mask(Row16(d, a.stride, a.full), _mm512_set1_ps(a.min_signal), _CMP_LT_OQ));
  if (signal == 0) {  // background
    std::fill_n(b->solved, kLanes, false);
    return;
  }
  V3 n{_mm512_set1_ps(a.toward.x()), _mm512_set1_ps(a.toward.y()), _mm512_set1_ps(a.toward.z())};
  if (a.guess) {
    const V3 guess{_mm512_sub_ps(Row16(d, a.stride, a.xp), Row16(d, a.stride, a.xm)),
                   _mm512_sub_ps(Row16(d, a.stride, a.yp), Row16(d, a.stride, a.ym)),
                   _mm512_sub_ps(Row16(d, a.stride, a.zp), Row16(d, a.stride, a.zm))};
    const __m512 norm = Norm16(guess);
    n = Blend16(_mm512_cmp_ps_mask(norm, _mm512_set1_ps(1e-6f), _CMP_GT_OQ), n, Divide16(guess, norm));
  }
  __mmask16 solved = signal;
  V3 u = n;
  for (int it = 0; it < 2; ++it) {
    u = Solve16(a, d, a.stride, n);
    __m512 norm;
    const __mmask16 ok = Usable16(u, 1e-9f, &norm);
    solved &= ok;
    n = Blend16(ok, n, Divide16(u, norm));
  }
  for (int c = 0; c < 3; ++c) {
    _mm512_storeu_ps(b->n[c], c == 0 ? n.x : c == 1 ? n.y : n.z);
    _mm512_storeu_ps(b->u[c], c == 0 ? u.x : c == 1 ? u.y : u.z);
  }
  for (int l = 0; l < kLanes; ++l) b->solved[l] = (solved >> l) & 1;
}

STAGE_AVX512 void DiffuseLast16(const DiffuseRow& a, int xb, int lanes, const float* lobe, float* d2, Batch* b) {
  const PhotometricTables::Data& t = *a.t;
  const int np = t.np;
  __mmask16 solved = 0, both = 0;
  for (int l = 0; l < lanes; ++l) {
    solved |= static_cast<__mmask16>(b->solved[l] ? 1u << l : 0u);
    both |= static_cast<__mmask16>(b->solved[l] && b->both[l] ? 1u << l : 0u);
  }
  if (solved == 0) return;
  V3 n{_mm512_loadu_ps(b->n[0]), _mm512_loadu_ps(b->n[1]), _mm512_loadu_ps(b->n[2])};
  V3 u{_mm512_loadu_ps(b->u[0]), _mm512_loadu_ps(b->u[1]), _mm512_loadu_ps(b->u[2])};
  const __m512 half_leak = _mm512_set1_ps(a.half_leak);
  for (int k = 0; k < np; ++k) {
    const size_t o = static_cast<size_t>(k) * a.stride + xb;
    const __m512 mixed =
        _mm512_sub_ps(_mm512_loadu_ps(a.rds + o), _mm512_mul_ps(half_leak, _mm512_loadu_ps(lobe + k * kLanes)));
    _mm512_storeu_ps(d2 + k * kLanes, _mm512_mask_blend_ps(both, _mm512_loadu_ps(a.rd + o), mixed));
  }
  if (both != 0) {
    const V3 u2 = Solve16(a, d2, kLanes, n);
    __m512 norm;
    const __mmask16 ok = both & Usable16(u2, 1e-9f, &norm);
    u = Blend16(ok, u, u2);
    n = Blend16(ok, n, Divide16(u2, norm));
  }
  const __m512i cells = Cells16(n, t.n);
  const __m512i base = _mm512_mullo_epi32(cells, _mm512_set1_epi32(3 * np));
  const __m512 ws = _mm512_set1_ps(a.ws);
  const __m512 copies = _mm512_mask_blend_ps(both, _mm512_set1_ps(1.f), _mm512_set1_ps(2.f));
  __m512 chi2 = _mm512_setzero_ps();
  const float* h = t.h.data();
  for (int k = 0; k < np; ++k) {
    const __m512i i = _mm512_add_epi32(base, _mm512_set1_epi32(3 * k));
    __m512 h0, h1;
    GatherPair16(h, i, &h0, &h1);
    const __m512 h2 = _mm512_i32gather_ps(_mm512_add_epi32(i, _mm512_set1_epi32(2)), h, 4);
    const __m512 pred = _mm512_mul_ps(
        ws, _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(u.x, h0), _mm512_mul_ps(u.y, h1)), _mm512_mul_ps(u.z, h2)));
    const __m512 e = _mm512_sub_ps(_mm512_loadu_ps(d2 + k * kLanes), pred);
    const __m512 dw = _mm512_loadu_ps(a.rdw + static_cast<size_t>(k) * a.stride + xb);
    chi2 = _mm512_add_ps(chi2, _mm512_mul_ps(_mm512_mul_ps(_mm512_mul_ps(e, e), copies), dw));
  }
  chi2 = _mm512_div_ps(chi2, _mm512_set1_ps(static_cast<float>(std::max(1, np - 3))));
  const __m512 own = _mm512_mask_blend_ps(
      both, _mm512_loadu_ps(a.own_cross + xb),
      _mm512_sub_ps(_mm512_loadu_ps(a.own_both + xb),
                    _mm512_div_ps(_mm512_mul_ps(half_leak, _mm512_loadu_ps(b->lobe_sum)), _mm512_set1_ps(3.f))));
  const __m512i hbase = _mm512_mullo_epi32(cells, _mm512_set1_epi32(3));
  const float* hsum = t.hsum.data();
  const __m512 hx = _mm512_i32gather_ps(hbase, hsum, 4);
  const __m512 hy = _mm512_i32gather_ps(_mm512_add_epi32(hbase, _mm512_set1_epi32(1)), hsum, 4);
  const __m512 hz = _mm512_i32gather_ps(_mm512_add_epi32(hbase, _mm512_set1_epi32(2)), hsum, 4);
  const __m512 shade = _mm512_mul_ps(ws, Dot16(n, hx, hy, hz));
  const __m512 albedo = _mm512_maskz_div_ps(_mm512_cmp_ps_mask(shade, _mm512_setzero_ps(), _CMP_GT_OQ), own, shade);
  // Only the solved lanes change.
  for (int c = 0; c < 3; ++c) _mm512_mask_storeu_ps(b->n[c], solved, c == 0 ? n.x : c == 1 ? n.y : n.z);
  _mm512_mask_storeu_ps(b->chi2, solved, chi2);
  _mm512_mask_storeu_ps(b->own_albedo, solved, albedo);
}

#endif  // STAGE_X86_64

// What the lobe's lookup reads for a row of a tile: the per-pair rows (np rows `stride` apart, from the tile's column
// 0), the moments' rows, and the constants.
struct LobeRow {
  const PhotometricTables::Data* t = nullptr;
  internal::LobeLimits limits;
  const float* rs = nullptr;   // the specular
  const float* rsw = nullptr;  // its inverse variance
  const float* mu = nullptr;   // the lobe's moments (kMoments rows)
  const float* v1 = nullptr;   // the first moment's variance
  size_t stride = 0;
  const float* coef = nullptr;            // per pair, the moments' coefficients (kMoments each)
  const Eigen::Vector3f* rays = nullptr;  // the image's rays from the camera (null: every view is `toward`)
  size_t ray_count = 0;
  Eigen::Vector3f toward = Eigen::Vector3f::UnitZ();
  float spec_scale = 1;
  int full = 0;
};

// Scratch of the lookup: the table's entry of each lane, entry-major (entry q of lane l at q * kLanes + l).
struct LobeScratch {
  std::vector<float> entry;  // spec_stride * kLanes
  std::vector<float> one;    // spec_stride rounded up to 16: one lane's entry
};

// a / |a| where |a| > 0 (else a), |a| as Eigen has it (x x + (y y + z z)). Without a branch, for the lanes' loops.
inline void Normalize(float& x, float& y, float& z) {
  const float n2 = x * x + (y * y + z * z);
  const float n = std::sqrt(n2);
  const bool positive = n2 > 0;
  x = positive ? x / n : x;
  y = positive ? y / n : y;
  z = positive ? z / n : z;
}

#if STAGE_X86_64
// The roughness search of LookUpLobesImpl (below) in AVX-512 lanes (GCC 12 does not vectorize its gathers): the same
// tests, so the same samples.
STAGE_AVX512 inline void SearchRoughness16(const float* spreads, int nj, const int* row, const int* first,
                                           const int* last, const uint8_t* ok, const float* spread, int* k0) {
  const __m512i vrow = _mm512_loadu_si512(row), vfirst = _mm512_loadu_si512(first), vlast = _mm512_loadu_si512(last);
  const __m512 vspread = _mm512_loadu_ps(spread);
  const __m512i vok = _mm512_cvtepu8_epi32(_mm_loadu_si128(reinterpret_cast<const __m128i*>(ok)));
  const __mmask16 live = _mm512_test_epi32_mask(vok, vok);
  __m512i vk0 = _mm512_set1_epi32(-1);
  __mmask16 open = live;  // lanes still searching
  for (int k = 0; k + 1 < nj; ++k) {
    const __m512i vk = _mm512_set1_epi32(k), vnext = _mm512_set1_epi32(k + 1);
    const __m512 hi = _mm512_i32gather_ps(_mm512_add_epi32(vrow, vnext), spreads, 4);
    const __mmask16 in_run =
        _mm512_cmp_epi32_mask(vk, vfirst, _MM_CMPINT_NLT) & _mm512_cmp_epi32_mask(vk, vlast, _MM_CMPINT_LT);
    const __mmask16 stop =
        _mm512_cmp_ps_mask(vspread, hi, _CMP_LE_OQ) | _mm512_cmp_epi32_mask(vnext, vlast, _MM_CMPINT_EQ);
    const __mmask16 take = open & in_run & stop;
    vk0 = _mm512_mask_mov_epi32(vk0, take, vk);
    open &= static_cast<__mmask16>(~take);
  }
  _mm512_storeu_si512(k0, vk0);
}
#endif  // STAGE_X86_64

// The specular of the solved lanes of a batch (row0: the image's index of the tile row's column 0): the lobe's mean
// direction and spread from its moments; per lane, its entry in the table (interpolated between the two roughness
// samples whose spreads bracket it and the four cells around the mean direction); then across the lanes, the lobe's
// intensity fitted to the images, its image per pair (lobe[k * kLanes + l], for the diffuse), the fit's residual, the
// mirror direction and the normal, and the noise of each. Each step runs over the lanes in loops the compiler makes
// vector code of, per lane the operations of the one-pixel-at-a-time code it replaces, so any target gives the same
// bits.
template <bool kAvx512>
__attribute__((always_inline)) inline void LookUpLobesImpl(const LobeRow& a, int xb, int lanes, size_t row0,
                                                           LobeScratch* scratch, float* lobe, Batch* b) {
  const PhotometricTables::Data& t = *a.t;
  const int np = t.np, ss = t.spec_stride;
  constexpr int kL = kLanes;
  // The moments: the mean direction, the first moment's length and the spread.
  const float* const mu = a.mu + xb;  // the moments' rows (a.stride apart), from the batch's first column
  const size_t mstride = a.stride;
  float mean[3][kL], length[kL], spread[kL];
  uint8_t ok[kL];
  for (int l = 0; l < kL; ++l) {
    const LobeMoments lobe_l =
        FromMoments([mu, mstride, l](int r) { return mu[static_cast<size_t>(r) * mstride + l]; });
    ok[l] = (l < lanes) & b->solved[l] & lobe_l.ok;
    length[l] = lobe_l.length;
    for (int i = 0; i < 3; ++i) mean[i][l] = lobe_l.mean[i];
    spread[l] = lobe_l.spread;
  }
  if (std::none_of(ok, ok + kL, [](uint8_t o) { return o != 0; })) {  // no lobe in the batch (the background)
    for (int l = 0; l < kL; ++l) {
      b->measured[l] = b->both[l] = false;
      b->lobe_sum[l] = 0;
    }
    return;
  }
  // The mean direction's octahedral coordinates (as OctEncode has them), across the lanes.
  float ou[kL], ov[kL];
  for (int l = 0; l < kL; ++l) {
    const float dx = mean[0][l], dy = mean[1][l], dz = mean[2][l];
    const float s = std::abs(dx) + std::abs(dy) + std::abs(dz);
    float x = dx / s, y = dy / s;
    const float ox = (1 - std::abs(y)) * (x >= 0 ? 1.f : -1.f), oy = (1 - std::abs(x)) * (y >= 0 ? 1.f : -1.f);
    if (dz < 0) {
      x = ox;
      y = oy;
    }
    // Kept within [0, 1] and a lane without a lobe (NaN: no mean direction) at 0, so that every lane's cell below is a
    // defined conversion to int; for a unit direction the clamp changes no cell and no weight.
    ou[l] = std::min(1.f, std::max(0.f, x * 0.5f + 0.5f));
    ov[l] = std::min(1.f, std::max(0.f, y * 0.5f + 0.5f));
  }
  // In passes over the lanes, so that the lanes' table reads overlap (one lane's chain of reads, cell to roughness to
  // entry, waited on memory at each link): the cells, whose spreads are fetched; the roughness samples; the corner
  // cells, whose entries at that roughness are fetched; then the entry, log roughness and its slope against the
  // spread. (Fetching the four cells' entries before the roughness was known was slower: 446 against 437 ms.)
  const float fsize = static_cast<float>(t.s);
  int cell[kL];
  for (int l = 0; l < kL; ++l) {  // every lane (in vector lanes), then the fetches of the lanes with a lobe
    const int u = std::clamp(static_cast<int>(ou[l] * fsize), 0, t.s - 1);
    const int v = std::clamp(static_cast<int>(ov[l] * fsize), 0, t.s - 1);
    cell[l] = v * t.s + u;
  }
  for (int l = 0; l < kL; ++l) {
    if (!ok[l]) continue;
    __builtin_prefetch(&t.spread[static_cast<size_t>(cell[l]) * t.j]);
    __builtin_prefetch(&t.spread[static_cast<size_t>(cell[l]) * t.j + t.j - 1]);
  }
  // The roughness whose spread matches, between the samples the cell has (clamped to the first and the last it has:
  // noise can take the spread a little past them): the first sample k from the cell's first on whose successor's
  // spread is not below the lobe's, or the last but one. Found for every lane at once, sample by sample (each
  // successor's spread gathered), rather than lane by lane, which waited on a branch per sample.
  int first[kL], last[kL], k0[kL];
  for (int l = 0; l < kL; ++l) {
    first[l] = t.first[static_cast<size_t>(cell[l])];
    last[l] = t.last[static_cast<size_t>(cell[l])];
    k0[l] = -1;
  }
  const float* const spreads = t.spread.data();
  const int nj = t.j;
  int row[kL];  // of the lane's cell in spreads
  for (int l = 0; l < kL; ++l) row[l] = cell[l] * nj;
  if constexpr (kAvx512) {
#if STAGE_X86_64
    SearchRoughness16(spreads, nj, row, first, last, ok, spread, k0);
#endif
  } else {
    for (int k = 0; k + 1 < nj; ++k) {
      for (int l = 0; l < kL; ++l) {
        const float hi = spreads[row[l] + k + 1];
        const bool take =
            (k0[l] < 0) & (ok[l] != 0) & (k >= first[l]) & (k < last[l]) & ((spread[l] <= hi) | (k + 1 == last[l]));
        k0[l] = take ? k : k0[l];
      }
    }
  }
  uint8_t known[kL], in_range[kL];
  float fr[kL];
  for (int l = 0; l < kL; ++l) {
    const int k = std::max(k0[l], 0);  // a sample to read (unknown lanes: their figures mean nothing)
    const float lo = spreads[row[l] + k], hi = spreads[row[l] + k + 1];
    const float raw_f = (spread[l] - lo) / std::max(1e-9f, hi - lo);
    known[l] = k0[l] >= 0;
    in_range[l] = known[l] & ((k > first[l]) | (raw_f >= 0)) & ((k + 1 < last[l]) | (raw_f <= 1));
    fr[l] = std::clamp(raw_f, 0.f, 1.f);
  }
  float* const entry = scratch->entry.data();
  float* const one = scratch->one.data();
  float log_alpha[kL], slope[kL];
  // The entry at this roughness, interpolated between the four cells around the mean direction (the nearest alone
  // where a neighbour has no lobe there): the cells and weights of every lane (in vector lanes), the fetches of the
  // known lanes' entries (so that the lanes' reads overlap), then lane by lane.
  float wus[kL], wvs[kL];
  int corner0[kL];  // index in spec of the first corner's entry at the lane's roughness
  for (int l = 0; l < kL; ++l) {
    const float fu = std::clamp(ou[l] * fsize - 0.5f, 0.f, t.s - 1.001f);
    const float fv = std::clamp(ov[l] * fsize - 0.5f, 0.f, t.s - 1.001f);
    const int cu0 = static_cast<int>(fu), cv0 = static_cast<int>(fv);
    wus[l] = fu - cu0;
    wvs[l] = fv - cv0;
    corner0[l] = ((cv0 * t.s + cu0) * nj + std::max(k0[l], 0)) * ss;
  }
  const int corner_step[4] = {0, nj * ss, t.s * nj * ss, (t.s + 1) * nj * ss};
  for (int l = 0; l < kL; ++l) {
    if (!known[l]) continue;
    for (int c = 0; c < 4; ++c) {
      const float* p = &t.spec[static_cast<size_t>(corner0[l] + corner_step[c])];
      __builtin_prefetch(p);
      __builtin_prefetch(p + ss + 4);
    }
  }
  for (int l = 0; l < kL; ++l) {
    log_alpha[l] = slope[l] = 0;
    if (!known[l]) continue;  // its entry is left as it was: nothing reads it
    const float f = fr[l];
    const float wu = wus[l], wv = wvs[l];
    const float* corner[4];
    bool corners = true;
    for (int c = 0; c < 4 && corners; ++c) {
      corner[c] = &t.spec[static_cast<size_t>(corner0[l] + corner_step[c])];
      corners = corner[c][4] > 0 && corner[c][ss + 4] > 0;
    }
    const float* e0 = &t.spec[(static_cast<size_t>(cell[l]) * t.j + k0[l]) * ss];
    // 16 of the entry's floats at a time, summed in registers (the table is padded for the last 16 read past its
    // end; the floats past ss are not used).
    const float g = 1 - f;
    for (int q0 = 0; q0 < ss; q0 += 16) {
      V16 sum;
      if (corners) {
        sum = V16{};
        for (int c = 0; c < 4; ++c) {
          const float wc = ((c & 1) ? wu : 1 - wu) * ((c >> 1) ? wv : 1 - wv);
          V16 ca, cb;
          STAGE_LOAD16(ca, corner[c] + q0);
          STAGE_LOAD16(cb, corner[c] + ss + q0);
          sum += wc * (g * ca + f * cb);
        }
      } else {
        V16 ca, cb;
        STAGE_LOAD16(ca, e0 + q0);
        STAGE_LOAD16(cb, e0 + ss + q0);
        sum = g * ca + f * cb;
      }
      std::memcpy(one + q0, &sum, sizeof sum);
    }
    for (int q = 0; q < ss; ++q) entry[q * kL + l] = one[q];
    const float* la = &t.log_alpha[static_cast<size_t>(k0[l])];
    log_alpha[l] = (1 - f) * la[0] + f * la[1];
    slope[l] = (la[1] - la[0]) / std::max(1e-9f, e0[ss + 3] - e0[3]);
  }
  // Across the lanes: the intensity, the lobe's shape fitted to the images (noise-weighted least squares).
  const float scale = a.spec_scale;
  float smm[kL] = {}, ssm[kL] = {};
  for (int k = 0; k < np; ++k) {
    const float* s = a.rs + k * a.stride + xb;
    const float* sw = a.rsw + k * a.stride + xb;
    const float* e = entry + (5 + k) * kL;
    for (int l = 0; l < kL; ++l) {
      const float mk = scale * e[l];
      smm[l] += sw[l] * mk * mk;
      ssm[l] += sw[l] * s[l] * mk;
    }
  }
  float rho[kL], chi2[kL] = {}, lobe_sum[kL] = {};
  for (int l = 0; l < kL; ++l) rho[l] = smm[l] > 0 ? std::max(0.f, ssm[l] / smm[l]) : 0.f;
  // Its image per pair and the residual; the noise of the second moment along the mean direction: the sum over the
  // pairs of its coefficient squared times the specular variance (with the mean direction q, the coefficient is
  // sum_j c_j(q) m_j).
  float c[6][kL], vs[kL] = {};
  for (int l = 0; l < kL; ++l) {
    const float qx = mean[0][l], qy = mean[1][l], qz = mean[2][l];
    c[0][l] = qx * qx;
    c[1][l] = qy * qy;
    c[2][l] = qz * qz;
    c[3][l] = 2 * qx * qy;
    c[4][l] = 2 * qy * qz;
    c[5][l] = 2 * qx * qz;
  }
  for (int k = 0; k < np; ++k) {
    const float* s = a.rs + k * a.stride + xb;
    const float* sw = a.rsw + k * a.stride + xb;
    const float* e = entry + (5 + k) * kL;
    const float* ck = a.coef + k * internal::kMoments + 4;
    float* lk = lobe + k * kL;
    for (int l = 0; l < kL; ++l) {
      lk[l] = rho[l] * scale * e[l];
      const float d = s[l] - lk[l];
      chi2[l] += sw[l] * d * d;
      lobe_sum[l] += lk[l];
      float q2k = 0;
      for (int j = 0; j < 6; ++j) q2k += c[j][l] * ck[j];
      vs[l] += q2k * q2k / sw[l];
    }
  }
  // The mirror direction, the normal (halfway to the view) and the noise of each.
  if (const size_t ahead = row0 + xb + 4 * kL; a.rays != nullptr && ahead + kL <= a.ray_count) {
    // The rays of a batch further on: they come from memory, one stream of many.
    const char* bytes = reinterpret_cast<const char*>(a.rays + ahead);
    for (size_t byte = 0; byte < kL * sizeof(Eigen::Vector3f); byte += 64) __builtin_prefetch(bytes + byte);
  }
  float v[3][kL];
  for (int l = 0; l < kL; ++l) {
    for (int i = 0; i < 3; ++i) v[i][l] = a.toward[i];
  }
  if (a.rays != nullptr) {
    static_assert(sizeof(Eigen::Vector3f) == 3 * sizeof(float), "the rays are read as an array of floats");
    const float* ray = a.rays[row0 + xb].data();  // the lanes' rays, 3 floats each
    for (int l = 0; l < lanes; ++l) {
      for (int i = 0; i < 3; ++i) v[i][l] = -ray[3 * l + i];
    }
  }
  const float dof = static_cast<float>(std::max(1, np - 4));
  const float* sfull = a.rs + a.full * a.stride + xb;
  const float* swfull = a.rsw + a.full * a.stride + xb;
  for (int l = 0; l < kL; ++l) {
    chi2[l] /= dof;
    float rx = mean[0][l] + entry[0 * kL + l], ry = mean[1][l] + entry[1 * kL + l], rz = mean[2][l] + entry[2 * kL + l];
    Normalize(rx, ry, rz);
    float nx = rx + v[0][l], ny = ry + v[1][l], nz = rz + v[2][l];
    Normalize(nx, ny, nz);
    b->ns[0][l] = nx;
    b->ns[1][l] = ny;
    b->ns[2][l] = nz;
    // The direction of m1 moves by its tangential noise over its own length; the normal halves the mirror
    // direction's angle.
    const float var_dir = 2.f / 3 * a.v1[xb + l] / (length[l] * length[l]);
    b->var_n[l] = var_dir / 4;
    b->var_log_alpha[l] = slope[l] * slope[l] * vs[l] / (mu[l] * mu[l]);
    b->rho[l] = rho[l];
  }
  // Every lane computed (in vector lanes); the lanes without a known lobe are not measured, and their fields mean
  // nothing.
  for (int l = 0; l < kL; ++l) {
    b->spec_bad_fit[l] = chi2[l] > 4;
    // With the lobe known and fitting, both polarizations hold the diffuse.
    b->both[l] = known[l] & (chi2[l] <= 4);
    b->lobe_sum[l] = b->both[l] ? lobe_sum[l] : 0.f;
  }
  // The roughness, the tests in 32-bit lanes, then with the byte flags: three loops, because GCC 12 vectorizes none
  // of them written as one.
  int32_t pass[kL];
  for (int l = 0; l < kL; ++l) b->alpha[l] = internal::PortableExp(log_alpha[l]);
  for (int l = 0; l < kL; ++l) {
    const float alpha = b->alpha[l];
    const float var_rho = smm[l] > 0 ? 1 / smm[l] : 1e30f;
    const float spec_snr = sfull[l] * std::sqrt(swfull[l]);
    pass[l] =
        internal::LobeMeasured(a.limits, spec_snr, b->var_n[l], rho[l], var_rho, b->var_log_alpha[l], alpha) ? 1 : 0;
    b->sigma_deg[l] = std::sqrt(b->var_n[l]) * 180 / kPi;
  }
  // A spread past the table's roughness range is noise (or a lobe outside 0.04..1): the lobe still stands for the
  // specular in the diffuse, but is not a measurement.
  for (int l = 0; l < kL; ++l) b->measured[l] = known[l] & in_range[l] & static_cast<uint8_t>(pass[l]);
}

void LookUpLobes(const LobeRow& a, int xb, int lanes, size_t row0, LobeScratch* scratch, float* lobe, Batch* b) {
  LookUpLobesImpl<false>(a, xb, lanes, row0, scratch, lobe, b);
}

#if STAGE_X86_64
STAGE_AVX512 void LookUpLobes16(const LobeRow& a, int xb, int lanes, size_t row0, LobeScratch* scratch, float* lobe,
                                Batch* b) {
  LookUpLobesImpl<true>(a, xb, lanes, row0, scratch, lobe, b);
}
#endif

// One thread's buffers for a tile: corrected rows (a ring of three per pattern), the per-pair rows, and the per-pixel
// scratch.
struct TileBuffers {
  std::vector<float> rows, kc, kd, rd, rs, rsv, rsw, rdw, rds;
  // Per column of the tile: the lobe's moments (kMoments rows), the noise of the first moment, and the own sums.
  std::vector<float> mu, v1, own_cross, own_both;
  std::vector<uint8_t> saturated;
  LobeScratch lobe_scratch;
  // The full-on pair's corrected rows (a ring of three each) and channel sums, and per row of the band the columns of
  // the tile from its first pixel to solve to its last, widened to whole batches (none: an empty span).
  std::vector<float> probe, probe_sums;
  std::vector<std::pair<int, int>> spans;
  Batch batch;
  std::vector<float> lobe_lanes, d2_lanes;

  void Resize(int patterns, int np, int spec_stride, size_t stride) {
    rows.resize(static_cast<size_t>(patterns) * 3 * stride);
    for (auto* v : {&kc, &kd}) v->resize(2 * stride);  // even rows, then odd ones
    for (auto* v : {&rd, &rs, &rsv, &rsw, &rdw, &rds}) v->resize(static_cast<size_t>(np) * stride);
    mu.resize(internal::kMoments * stride);
    for (auto* v : {&v1, &own_cross, &own_both}) v->resize(stride);
    saturated.resize(stride);
    for (auto* v : {&lobe_lanes, &d2_lanes}) v->resize(static_cast<size_t>(np) * kLanes);
    probe.resize(2 * 3 * stride);
    probe_sums.resize(2 * stride);
    lobe_scratch.entry.resize(static_cast<size_t>(spec_stride) * kLanes);
    lobe_scratch.one.resize((static_cast<size_t>(spec_stride) + 15) / 16 * 16);
  }
};

}  // namespace

absl::StatusOr<std::shared_ptr<const PhotometricTables>> PhotometricTables::Build(const LightModel& light,
                                                                                  const PhotometricCamera& camera,
                                                                                  const PhotometricOptions& options) {
  auto twins = internal::PairPatterns(light);
  if (!twins.ok()) return twins.status();
  std::shared_ptr<PhotometricTables> tables(new PhotometricTables());
  tables->data_ = std::make_unique<Data>();
  Data& d = *tables->data_;
  d.twins = *twins;
  d.pm = internal::MakePatternMatrix(light, d.twins);
  d.np = d.pm.np;
  d.patterns = static_cast<int>(light.patterns.size());
  const int np = d.np;
  const UnitView origin = light.ViewFromOrigin();
  d.view = camera.position_mm.normalized().cast<float>();

  // Diffuse. Weights as the noise model has them for a surface of albedo sum 1: shot noise (the level) and read noise.
  d.n = kDiffuseCells;
  const size_t cells = static_cast<size_t>(d.n) * d.n;
  d.h.resize(cells * 3 * np);
  d.m.resize(cells * 3 * np);
  d.hsum.resize(cells * 3);
  const double read_dn2 = internal::ReadVarianceDn2(camera);
  const double floor = read_dn2 * camera.gain_e_per_dn / std::max(1e-9, camera.white_scale);
  internal::ParallelRows(d.n, options.threads, [&](int v0, int v1) {
    std::vector<float> hp(3 * static_cast<size_t>(np));
    for (int v = v0; v < v1; ++v) {
      for (int u = 0; u < d.n; ++u) {
        const size_t c = static_cast<size_t>(v) * d.n + u;
        const Eigen::Vector3f n = OctDecode({(u + 0.5f) / d.n, (v + 0.5f) / d.n});
        internal::DiffuseFromView(origin, d.pm, n, hp.data());
        Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
        Eigen::Vector3d sum = Eigen::Vector3d::Zero();
        std::vector<double> w(static_cast<size_t>(np));
        for (int p = 0; p < np; ++p) {
          const Eigen::Vector3d hv(hp[3 * p], hp[3 * p + 1], hp[3 * p + 2]);
          w[static_cast<size_t>(p)] = 1.0 / (std::max(0.0, n.cast<double>().dot(hv)) + floor);
          a += w[static_cast<size_t>(p)] * hv * hv.transpose();
          sum += hv;
        }
        const Eigen::Matrix3d inv = (a + 1e-12 * Eigen::Matrix3d::Identity()).inverse();
        for (int p = 0; p < np; ++p) {
          const Eigen::Vector3d hv(hp[3 * p], hp[3 * p + 1], hp[3 * p + 2]);
          const Eigen::Vector3d col = inv * hv * w[static_cast<size_t>(p)];
          for (int k = 0; k < 3; ++k) {
            d.h[(c * np + p) * 3 + k] = hp[3 * p + k];
            d.m[(c * 3 + k) * np + p] = static_cast<float>(col[k]);
          }
        }
        for (int k = 0; k < 3; ++k) d.hsum[c * 3 + k] = static_cast<float>(sum[k]);
      }
    }
  });

  // Specular: for every measured mean direction and roughness, the mirror direction whose lobe has that mean (found by
  // fixed-point steps through the exact model), and what that lobe looks like.
  d.s = kSpecularCells;
  d.j = kAlphas;
  for (int k = 0; k < d.j; ++k) {
    d.log_alpha.push_back(internal::PortableLog(kAlphaMin) +
                          (internal::PortableLog(kAlphaMax) - internal::PortableLog(kAlphaMin)) * k / (d.j - 1));
  }
  d.spec_stride = 5 + np;
  d.spec.assign(static_cast<size_t>(d.s) * d.s * d.j * d.spec_stride + kSpecPad, 0.f);
  const Eigen::Vector3f v = d.view;
  // The largest total each roughness reaches anywhere: a lobe whose total is far below it falls mostly off the dome.
  std::vector<float> best(static_cast<size_t>(d.j), 0.f);
  std::mutex best_mutex;
  internal::ParallelRows(d.s, options.threads, [&](int v0, int v1) {
    std::vector<float> m(static_cast<size_t>(np));
    std::vector<float> local(static_cast<size_t>(d.j), 0.f);
    for (int row = v0; row < v1; ++row) {
      for (int col = 0; col < d.s; ++col) {
        const size_t c = static_cast<size_t>(row) * d.s + col;
        const Eigen::Vector3f target = OctDecode({(col + 0.5f) / d.s, (row + 0.5f) / d.s});
        for (int k = 0; k < d.j; ++k) {
          const float alpha = internal::PortableExp(d.log_alpha[static_cast<size_t>(k)]);
          Eigen::Vector3f r = target;
          LobeMoments mom;
          for (int it = 0; it < 8; ++it) {
            const Eigen::Vector3f n = (r + v).normalized();
            if (n.dot(v) <= 0.02f) break;
            internal::SpecularFromView(origin, d.pm, n, v, alpha, m.data());
            mom = Moments(d.pm, m.data());
            if (!mom.ok) break;
            r = (r + (target - Eigen::Vector3f(mom.mean[0], mom.mean[1], mom.mean[2]))).normalized();
          }
          if (!mom.ok) continue;
          // The last step's lobe (at r): where it lands must be the target, else the direction is out of reach.
          const Eigen::Vector3f n = (r + v).normalized();
          internal::SpecularFromView(origin, d.pm, n, v, alpha, m.data());
          mom = Moments(d.pm, m.data());
          const Eigen::Vector3f mean(mom.mean[0], mom.mean[1], mom.mean[2]);
          if (!mom.ok || !(mean.dot(target) >= kCosReach)) continue;
          float* e = &d.spec[(c * d.j + k) * d.spec_stride];
          const Eigen::Vector3f dr = r - target;
          e[0] = dr.x(), e[1] = dr.y(), e[2] = dr.z();
          e[3] = mom.spread;
          e[4] = mom.mu0;
          std::copy(m.begin(), m.end(), e + 5);
          local[static_cast<size_t>(k)] = std::max(local[static_cast<size_t>(k)], mom.mu0);
        }
      }
    }
    std::lock_guard<std::mutex> lock(best_mutex);
    for (int k = 0; k < d.j; ++k)
      best[static_cast<size_t>(k)] = std::max(best[static_cast<size_t>(k)], local[static_cast<size_t>(k)]);
  });
  for (size_t c = 0; c < static_cast<size_t>(d.s) * d.s; ++c) {
    for (int k = 0; k < d.j; ++k) {
      float* e = &d.spec[(c * d.j + k) * d.spec_stride];
      if (e[4] < 0.25f * best[static_cast<size_t>(k)]) std::fill(e, e + d.spec_stride, 0.f);
    }
  }
  d.first.assign(static_cast<size_t>(d.s) * d.s, -1);
  d.last.assign(static_cast<size_t>(d.s) * d.s, -1);
  d.spread.assign(static_cast<size_t>(d.s) * d.s * d.j, 0.f);
  for (size_t c = 0; c < static_cast<size_t>(d.s) * d.s; ++c) {
    for (int k = 0; k < d.j; ++k) {
      const float* e = &d.spec[(c * d.j + k) * d.spec_stride];
      d.spread[c * d.j + k] = e[3];
      if (e[4] > 0) {
        if (d.first[c] < 0) d.first[c] = k;
        d.last[c] = k;
      } else if (d.first[c] >= 0) {
        break;
      }
    }
  }
  return std::shared_ptr<const PhotometricTables>(std::move(tables));
}

absl::StatusOr<PhotometricMaps> SolvePhotometricFast(const LightModel& light, const PhotometricTables& tables,
                                                     const CycleFrames& cycle, const RawCorrection& correction,
                                                     const PhotometricCamera& camera,
                                                     const PhotometricOptions& options) {
  PhotometricMaps maps;
  if (auto s = SolvePhotometricFast(light, tables, cycle, correction, camera, options, &maps); !s.ok()) return s;
  return maps;
}

absl::Status SolvePhotometricFast(const LightModel& light, const PhotometricTables& tables, const CycleFrames& cycle,
                                  const RawCorrection& correction, const PhotometricCamera& camera,
                                  const PhotometricOptions& options, PhotometricMaps* out) {
  const PhotometricTables::Data& t = tables.data();
  const int np = t.np;
  const int w = cycle.width, h = cycle.height;
  if (t.patterns != static_cast<int>(light.patterns.size())) {
    return absl::InvalidArgumentError(absl::StrCat("photometric stereo: the tables are for ", t.patterns,
                                                   " patterns, the light model has ", light.patterns.size()));
  }
  if (w < 2 || h < 2) {
    return absl::InvalidArgumentError(absl::StrCat("photometric stereo: ", w, "x", h, " is too small (2x2 at least)"));
  }
  if (cycle.raw.size() != light.patterns.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("photometric stereo: ", cycle.raw.size(), " images for ", light.patterns.size(), " patterns"));
  }
  for (size_t i = 0; i < cycle.raw.size(); ++i) {
    if (cycle.raw[i].size() != static_cast<size_t>(w) * h) {
      return absl::InvalidArgumentError(
          absl::StrCat("photometric stereo: the image of pattern \"", light.patterns[i].name, "\" is not ", w, "x", h));
    }
  }
  if (correction.flat_field != nullptr && (correction.flat_field->width != w || correction.flat_field->height != h ||
                                           correction.flat_field->channels != 1)) {
    return absl::InvalidArgumentError(absl::StrCat("photometric stereo: the flat field is not ", w, "x", h));
  }
  if (!camera.rays.empty() && camera.rays.size() != static_cast<size_t>(w) * h) {
    return absl::InvalidArgumentError(
        absl::StrCat("photometric stereo: ", camera.rays.size(), " camera rays for ", w, "x", h, " pixels"));
  }
  const internal::Twins& tw = t.twins;

  PhotometricMaps& m = *out;
  internal::PrepareMaps(w, h, &m);  // every pixel is written below
  float* var_n = internal::Work(&m, internal::kVarNormal);
  float* var_log_alpha = internal::Work(&m, internal::kVarLogAlpha);
  float* own_albedo = internal::Work(&m, internal::kOwnAlbedo);  // each pixel's albedo in the colour it measures

  const float k_leak = static_cast<float>(camera.cross_leak / std::max(1e-9, 1 - camera.cross_leak));
  const float spec_gain = static_cast<float>(1 / std::max(1e-9, 1 - camera.cross_leak));
  const float leak = static_cast<float>(camera.cross_leak);
  const float g = static_cast<float>(camera.gain_e_per_dn);
  const float read_dn2 = internal::ReadVarianceDn2(camera);
  const float ws = static_cast<float>(camera.white_scale);
  const float spec_scale = 3 * 2 * kPi * ws;
  const float black = static_cast<float>(correction.black_level_dn);
  // Clipped: the raw level of saturation (the camera's saturation_dn above its black level).
  const auto top =
      static_cast<uint16_t>(std::clamp(std::lround(camera.saturation_dn + correction.black_level_dn), 1L, 65535L));
  const Eigen::Matrix3f to_camera = camera.world_to_camera.cast<float>();
  const Eigen::Vector3f toward = camera.position_mm.normalized().cast<float>();
  const int patterns = static_cast<int>(light.patterns.size());
  // The channel sum of a bilinear demosaic at a pixel is its own value plus, on a red or blue site, a quarter of its
  // 8 neighbours, on a green site half of its 4 edge neighbours (a mono sensor: three times its value).
  const bool mono = cycle.mosaic.mono;

  // Each band of rows is solved in column tiles, so that a tile's working set (the corrected rows of every pattern
  // and the per-pair rows: about 1 KB a column) stays in the core's L2 cache between the row loops
  // that write it and the per-pixel loop that reads it; whole rows (3.6 MB at 4096 columns) went out to memory in
  // between.
  const int tile = std::min(w, internal::FastTileColumns());
  // Buffers are `stride` floats apart: the tile, a column of halo either side, rounded up, plus a cache line (rows a
  // power of two apart would fall in one set of the L1 cache, and the per-pixel reads across them would evict each
  // other).
  const size_t stride = (static_cast<size_t>(tile) + 2 + 15) / 16 * 16 + 16;
  // Per pattern pair: the coefficients of the lobe's moments (pair-major, kMoments each), and the first moment's
  // squared (summed over x, y, z).
  std::vector<float> coef(static_cast<size_t>(np) * internal::kMoments), q1(static_cast<size_t>(np));
  for (int k = 0; k < np; ++k) {
    for (int r = 0; r < internal::kMoments; ++r) {
      coef[static_cast<size_t>(k) * internal::kMoments + r] = t.pm.moments(r, k);
    }
    q1[static_cast<size_t>(k)] = t.pm.moments(1, k) * t.pm.moments(1, k) + t.pm.moments(2, k) * t.pm.moments(2, k) +
                                 t.pm.moments(3, k) * t.pm.moments(3, k);
  }
  // The least float not below the least signal: a float value is below one exactly when it is below the other.
  const float min_signal = internal::FloatAtLeast(internal::MinSignalDn(options, camera));
  internal::ParallelRows(h, options.threads, [&](int y0, int y1) {
    // Per thread, reused from band to band and solve to solve (fresh buffers each band cost page faults).
    static thread_local TileBuffers buffers;
    buffers.Resize(patterns, np, t.spec_stride, stride);
    buffers.spans.resize(static_cast<size_t>(y1 - y0));
    // Corrected rows of every pattern (with a column of halo either side), a ring of three (y - 1, y, y + 1: each row
    // corrected once).
    float* const rows = buffers.rows.data();
    float* const kc = buffers.kc.data();
    float* const kd = buffers.kd.data();
    float* const rd = buffers.rd.data();
    float* const rs = buffers.rs.data();
    float* const rsv = buffers.rsv.data();
    float* const rsw = buffers.rsw.data();
    float* const rdw = buffers.rdw.data();
    float* const rds = buffers.rds.data();
    float* const mu = buffers.mu.data();
    float* const v1 = buffers.v1.data();
    float* const own_cross = buffers.own_cross.data();
    float* const own_both = buffers.own_both.data();
    uint8_t* const saturated = buffers.saturated.data();
    // The per-pixel steps' batch, the lobes of its pixels and the diffuse data solved again (pair-major, kLanes a
    // pair).
    Batch& batch = buffers.batch;
    float* const lobe_lanes = buffers.lobe_lanes.data();
    float* const d2_lanes = buffers.d2_lanes.data();
    const DiffuseRow da{.t = &t,
                        .rd = rd,
                        .rds = rds,
                        .rdw = rdw,
                        .own_cross = own_cross,
                        .own_both = own_both,
                        .stride = stride,
                        .ws = ws,
                        .half_leak = 0.5f * (1 + leak),
                        .min_signal = min_signal,
                        .full = tw.full,
                        .guess = tw.xp >= 0 && tw.xm >= 0 && tw.yp >= 0 && tw.ym >= 0 && tw.zp >= 0 && tw.zm >= 0,
                        .xp = tw.xp,
                        .xm = tw.xm,
                        .yp = tw.yp,
                        .ym = tw.ym,
                        .zp = tw.zp,
                        .zm = tw.zm,
                        .toward = toward};
    const LobeRow la{.t = &t,
                     .limits = internal::LobeLimits(options),
                     .rs = rs,
                     .rsw = rsw,
                     .mu = mu,
                     .v1 = v1,
                     .stride = stride,
                     .coef = coef.data(),
                     .rays = camera.rays.empty() ? nullptr : camera.rays.data(),
                     .ray_count = camera.rays.size(),
                     .toward = toward,
                     .spec_scale = spec_scale,
                     .full = tw.full};
#if STAGE_X86_64
    const bool avx512 = internal::FastVectorKernels() && internal::FastVectorKernelsAvailable();
#endif
    auto row = [&](int p, int y) {  // the ring's slot of row y of pattern p; column x0 - 1 first
      return &rows[(static_cast<size_t>(p) * 3 + static_cast<size_t>((y + 3) % 3)) * stride];
    };
    for (int x0 = 0; x0 < w; x0 += tile) {
      const int x1 = std::min(w, x0 + tile), tw_cols = x1 - x0;
      // Row y's columns x0 - 1 .. x1 (the image's edges mirrored) of pattern p, corrected, into `slot`.
      auto correct_into = [&](int p, int y, float* slot) {
        const int yy = y < 0 ? -y : y >= h ? 2 * h - 2 - y : y;
        const size_t r0 = static_cast<size_t>(yy) * w;
        const float* flat = correction.flat_field != nullptr ? &correction.flat_field->pixels[r0] : nullptr;
        const int xl = x0 > 0 ? x0 - 1 : 1, xr = x1 < w ? x1 : w - 2;  // the halo's source columns
        const uint16_t* raw = &cycle.raw[static_cast<size_t>(p)][r0];
        CorrectRow(raw + x0, flat != nullptr ? flat + x0 : nullptr, black, tw_cols, slot + 1);
        if (yy + 1 < h) {
          const char* next = reinterpret_cast<const char*>(raw + w + x0);
          for (int b = 0; b < tw_cols * 2; b += 64) __builtin_prefetch(next + b);
        }
        CorrectRow(raw + xl, flat != nullptr ? flat + xl : nullptr, black, 1, slot);
        CorrectRow(raw + xr, flat != nullptr ? flat + xr : nullptr, black, 1, slot + 1 + tw_cols);
      };
      // The demosaic's weights along the tile's even rows and its odd ones (the mosaic repeats every two rows).
      for (int parity = 0; parity < 2; ++parity) {
        for (int x = x0; x < x1; ++x) {
          const bool green = cycle.mosaic.Color(x, parity) == 1;
          kc[parity * stride + static_cast<size_t>(x - x0)] = mono ? 0 : green ? 0.5f : 0.25f;
          kd[parity * stride + static_cast<size_t>(x - x0)] = mono || green ? 0 : 0.25f;
        }
      }
      auto kc_of = [&](int y) { return kc + static_cast<size_t>(y & 1) * stride; };
      auto kd_of = [&](int y) { return kd + static_cast<size_t>(y & 1) * stride; };
      // Where the rows of the tile have a pixel to solve: the full-on pair's diffuse, computed with the functions and
      // values the row loops below use (so the same bits), against the least signal. The row loops and the per-pixel
      // steps run only from a row's first such pixel to its last (in whole batches); the rows without one (the
      // background) skip them.
      {
        const int pair[2] = {tw.cross[static_cast<size_t>(tw.full)], tw.parallel[static_cast<size_t>(tw.full)]};
        auto probe = [&](int i, int y) { return &buffers.probe[(static_cast<size_t>(i) * 3 + (y + 3) % 3) * stride]; };
        for (int y = y0 - 1; y <= y0; ++y) {
          for (int i = 0; i < 2; ++i) correct_into(pair[i], y, probe(i, y));
        }
        for (int y = y0; y < y1; ++y) {
          for (int i = 0; i < 2; ++i) correct_into(pair[i], y + 1, probe(i, y + 1));
          float* dc = &buffers.probe_sums[0];
          float* dp = &buffers.probe_sums[stride];
          ChannelSumRow(probe(0, y - 1) + 1, probe(0, y) + 1, probe(0, y + 1) + 1, kc_of(y), kd_of(y), mono ? 3.f : 1.f,
                        tw_cols, dc);
          ChannelSumRow(probe(1, y - 1) + 1, probe(1, y) + 1, probe(1, y + 1) + 1, kc_of(y), kd_of(y), mono ? 3.f : 1.f,
                        tw_cols, dp);
          int lo = tw_cols, hi = 0;
          for (int x = 0; x < tw_cols; ++x) {
            if (!(dc[x] - k_leak * (dp[x] - dc[x]) < da.min_signal)) {  // as ChannelSumPairRow and DiffuseFirst
              lo = std::min(lo, x);
              hi = x + 1;
            }
          }
          buffers.spans[static_cast<size_t>(y - y0)] =
              hi > lo ? std::pair(lo / kLanes * kLanes, std::min(tw_cols, (hi + kLanes - 1) / kLanes * kLanes))
                      : std::pair(0, 0);
        }
      }
      int corrected_through = y0 - 2;  // the ring holds the corrected rows up to this one (the last three)
      for (int y = y0; y < y1; ++y) {
        std::fill_n(saturated, tw_cols, 0);
        for (int p = 0; p < patterns; ++p) {
          SaturationRow(&cycle.raw[static_cast<size_t>(p)][static_cast<size_t>(y) * w + x0], top, tw_cols, saturated);
        }
        // Zero where nothing is solved (the maps' memory is reused from solve to solve), a row at a time; a row with
        // nothing to solve straight to memory.
        const size_t row0 = static_cast<size_t>(y) * w + x0;
        const auto [lo, hi] = buffers.spans[static_cast<size_t>(y - y0)];
        const bool signal = hi > lo;
        auto zero = [&](float* p, size_t n) {
          if (signal) {
            std::fill_n(p, n, 0.f);
          } else {
            internal::StreamZeros(p, n);
          }
        };
        for (Image* image : {&m.diffuse_normal_world, &m.diffuse_normal_camera, &m.specular_normal_raw}) {
          zero(&image->pixels[3 * row0], 3 * static_cast<size_t>(tw_cols));
        }
        for (Image* image : {&m.specular, &m.roughness, &m.specular_sigma, &m.confidence, &m.fit_residual}) {
          zero(&image->pixels[row0], static_cast<size_t>(tw_cols));
        }
        zero(&own_albedo[row0], static_cast<size_t>(tw_cols));
        for (int xt = 0; xt < tw_cols; ++xt) {
          if (xt == lo) xt = hi;  // the span's pixels are flagged below
          if (xt < tw_cols) m.flags[row0 + xt] = (saturated[xt] ? kSaturated : 0) | kLowSignal;
        }
        if (!signal) continue;
        const int span = hi - lo;
        for (int r = std::max(corrected_through + 1, y - 1); r <= y + 1; ++r) {
          for (int p = 0; p < patterns; ++p) correct_into(p, r, row(p, r));
        }
        corrected_through = y + 1;
        for (int k = 0; k < np; ++k) {
          const size_t o = static_cast<size_t>(k) * stride + lo;
          const int pc = tw.cross[static_cast<size_t>(k)], pp = tw.parallel[static_cast<size_t>(k)];
          const PairRows rows3{.cross = {row(pc, y - 1) + 1 + lo, row(pc, y) + 1 + lo, row(pc, y + 1) + 1 + lo},
                               .parallel = {row(pp, y - 1) + 1 + lo, row(pp, y) + 1 + lo, row(pp, y + 1) + 1 + lo}};
          ChannelSumPairRow(rows3, kc_of(y) + lo, kd_of(y) + lo, mono ? 3.f : 1.f, k_leak, spec_gain, 1 / g, read_dn2,
                            span, &rd[o], &rs[o], &rsv[o], &rsw[o], &rdw[o], &rds[o]);
        }
        // The row's linear sums over the pattern pairs: the lobe's moments, the first moment's noise, and the own
        // sums.
        MomentRows(rs + lo, rsv + lo, stride, np, coef.data(), q1.data(), span, mu + lo, v1 + lo);
        std::fill_n(own_cross + lo, span, 0.f);
        std::fill_n(own_both + lo, span, 0.f);
        for (int k = 0; k < np; ++k) {
          const int pc = tw.cross[static_cast<size_t>(k)], pp = tw.parallel[static_cast<size_t>(k)];
          OwnRow(row(pc, y) + 1 + lo, row(pp, y) + 1 + lo, k_leak, span, own_cross + lo, own_both + lo);
        }
        for (int xb = lo; xb < hi; xb += kLanes) {
          const int lanes = std::min(kLanes, tw_cols - xb);
          // Diffuse: a first guess from the gradients, then u = M(n) d twice, across the batch.
#if STAGE_X86_64
          if (avx512) {
            DiffuseFirst16(da, xb, lanes, &batch);
          } else {
            DiffuseFirst(da, xb, lanes, &batch);
          }
#else
          DiffuseFirst(da, xb, lanes, &batch);
#endif
          // Specular: the lobe's moments, then through the table to its mirror direction, roughness and intensity.
#if STAGE_X86_64
          if (avx512) {
            LookUpLobes16(la, xb, lanes, row0, &buffers.lobe_scratch, lobe_lanes, &batch);
          } else {
            LookUpLobes(la, xb, lanes, row0, &buffers.lobe_scratch, lobe_lanes, &batch);
          }
#else
          LookUpLobes(la, xb, lanes, row0, &buffers.lobe_scratch, lobe_lanes, &batch);
#endif
          uint8_t lane_flags[kLanes];
          for (int l = 0; l < lanes; ++l) {
            const int xt = xb + l;
            const int x = x0 + xt;
            const size_t i = row0 + xt;
            uint8_t flags = saturated[xt] ? kSaturated : 0;
            if (!batch.solved[l]) {
              m.flags[i] = flags | kLowSignal;
              continue;
            }
            if (batch.measured[l]) {
              if (batch.spec_bad_fit[l]) flags |= kSpecularBadFit;
              float* ns = m.specular_normal_raw.at(x, y);
              for (int c = 0; c < 3; ++c) ns[c] = batch.ns[c][l];
              m.specular.at(x, y)[0] = batch.rho[l];
              m.roughness.at(x, y)[0] = batch.alpha[l];
              m.specular_sigma.at(x, y)[0] = batch.sigma_deg[l];
              var_n[i] = batch.var_n[l];
              var_log_alpha[i] = batch.var_log_alpha[l];
            } else {
              flags |= kNoSpecular;
            }
            lane_flags[l] = flags;
          }
          // Diffuse again from both polarizations where the lobe is known; the fit's residual and the own albedo.
#if STAGE_X86_64
          if (avx512) {
            DiffuseLast16(da, xb, lanes, lobe_lanes, d2_lanes, &batch);
          } else {
            DiffuseLast(da, xb, lanes, lobe_lanes, d2_lanes, &batch);
          }
#else
          DiffuseLast(da, xb, lanes, lobe_lanes, d2_lanes, &batch);
#endif
          for (int l = 0; l < lanes; ++l) {
            if (!batch.solved[l]) continue;
            const int xt = xb + l;
            const int x = x0 + xt;
            const size_t i = row0 + xt;
            uint8_t flags = lane_flags[l];
            const float chi2 = batch.chi2[l];
            if (chi2 > 4) flags |= kBadFit;
            own_albedo[i] = batch.own_albedo[l];
            const Eigen::Vector3f n(batch.n[0][l], batch.n[1][l], batch.n[2][l]);
            const Eigen::Vector3f nc = to_camera * n;
            std::copy(n.data(), n.data() + 3, m.diffuse_normal_world.at(x, y));
            std::copy(nc.data(), nc.data() + 3, m.diffuse_normal_camera.at(x, y));
            m.fit_residual.at(x, y)[0] = chi2;
            m.confidence.at(x, y)[0] =
                internal::Confidence(rd[static_cast<size_t>(tw.full) * stride + xt], g, read_dn2, chi2, flags);
            m.flags[i] = flags;
          }
        }
      }
    }
    internal::StreamFence();  // the streamed zeros, before other threads read the maps
  });

  // RGB albedo: each pixel's own colour as solved, the others from its neighbours' hue.
  internal::DemosaicAlbedo(cycle.mosaic, own_albedo, static_cast<float>(options.max_albedo), options.threads, &m);
  internal::RegularizeSpecular(options.specular_filter_radius, options.threads, to_camera, &m);
  return absl::OkStatus();
}

}  // namespace stage::processing
