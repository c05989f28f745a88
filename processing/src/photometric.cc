// Photometric stereo under spherical gradient illumination: see photometric.h.
#include "stage/processing/photometric.h"

#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gap_fill.h"
#include "photometric_internal.h"
#include "stage/common/ggx.h"
#include "stage/processing/visual_hull.h"

namespace stage::processing {
namespace internal {

absl::StatusOr<Twins> PairPatterns(const LightModel& light) {
  Twins t;
  for (size_t i = 0; i < light.patterns.size(); ++i) {
    const LightPattern& p = light.patterns[i];
    if (p.parallel) continue;
    std::string suffix = p.name;
    if (absl::StartsWith(suffix, "cross-")) suffix = suffix.substr(6);
    auto twin = light.Find("parallel-" + suffix);
    if (!twin.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("pattern \"", p.name, "\" has no parallel twin \"parallel-", suffix, "\""));
    }
    // Parallel - cross holds the specular only when both drive their emitters alike.
    const std::vector<double>& a = p.weights;
    const std::vector<double>& b = light.patterns[static_cast<size_t>(*twin)].weights;
    for (size_t l = 0; l < a.size() && l < b.size(); ++l) {
      if (std::abs(a[l] - b[l]) > 1e-6) {
        return absl::InvalidArgumentError(absl::StrCat("patterns \"", p.name, "\" and \"", light.patterns[*twin].name,
                                                       "\" drive unit ", l, " differently (", a[l], ", ", b[l],
                                                       "): photometric stereo pairs each gradient in both "
                                                       "polarizations"));
      }
    }
    const int k = static_cast<int>(t.cross.size());
    t.cross.push_back(static_cast<int>(i));
    t.parallel.push_back(*twin);
    if (suffix == "full") t.full = k;
    if (suffix == "x+") t.xp = k;
    if (suffix == "x-") t.xm = k;
    if (suffix == "y+") t.yp = k;
    if (suffix == "y-") t.ym = k;
    if (suffix == "z+") t.zp = k;
    if (suffix == "z-") t.zm = k;
  }
  if (t.cross.size() < 4) return absl::InvalidArgumentError("photometric stereo needs at least 4 cross patterns");
  if (t.full < 0) return absl::InvalidArgumentError("the pattern set has no full-on pattern (\"cross-full\")");
  return t;
}

// Pattern weights unit-major (w[l * np + p]) for the paired patterns, and the coefficients that turn the specular
// images into the lobe's first moments (sum_p c_p w_p(l) ~ 1, x_l, y_l, z_l over the units).
PatternMatrix MakePatternMatrix(const LightModel& light, const Twins& t) {
  PatternMatrix m;
  m.np = static_cast<int>(t.cross.size());
  m.units = light.units();
  m.cross.resize(static_cast<size_t>(m.np) * m.units);
  m.parallel.resize(m.cross.size());
  Eigen::MatrixXd w(m.np, m.units);
  for (int p = 0; p < m.np; ++p) {
    for (int l = 0; l < m.units; ++l) {
      const double c = light.patterns[static_cast<size_t>(t.cross[p])].weights[static_cast<size_t>(l)];
      const double q = light.patterns[static_cast<size_t>(t.parallel[p])].weights[static_cast<size_t>(l)];
      m.cross[static_cast<size_t>(l) * m.np + p] = static_cast<float>(c);
      m.parallel[static_cast<size_t>(l) * m.np + p] = static_cast<float>(q);
      w(p, l) = q;
    }
  }
  Eigen::MatrixXd f(kMoments, m.units);
  for (int l = 0; l < m.units; ++l) {
    const Eigen::Vector3d& d = light.directions[static_cast<size_t>(l)];
    f.col(l) << 1, d.x(), d.y(), d.z(), d.x() * d.x(), d.y() * d.y(), d.z() * d.z(), d.x() * d.y(), d.y() * d.z(),
        d.x() * d.z();
  }
  // c W = f in the least-squares sense: c = f W^T (W W^T)^-1.
  const Eigen::MatrixXd gram = w * w.transpose() + 1e-9 * Eigen::MatrixXd::Identity(m.np, m.np);
  m.moments = (gram.ldlt().solve(w * f.transpose())).transpose().cast<float>();
  return m;
}

void DiffuseFromView(const UnitView& view, const PatternMatrix& pm, const Eigen::Vector3f& n, float* hp) {
  std::fill(hp, hp + 3 * pm.np, 0.f);
  for (int l = 0; l < pm.units; ++l) {
    const float g = view.gain[static_cast<size_t>(l)];
    const Eigen::Vector3f& d = view.direction[static_cast<size_t>(l)];
    if (g == 0 || n.dot(d) <= 0) continue;
    const float* w = &pm.cross[static_cast<size_t>(l) * pm.np];
    const float gx = g * d.x(), gy = g * d.y(), gz = g * d.z();
    for (int p = 0; p < pm.np; ++p) {
      hp[3 * p] += w[p] * gx;
      hp[3 * p + 1] += w[p] * gy;
      hp[3 * p + 2] += w[p] * gz;
    }
  }
}

void SpecularFromView(const UnitView& view, const PatternMatrix& pm, const Eigen::Vector3f& n, const Eigen::Vector3f& v,
                      float alpha, float* m) {
  std::fill(m, m + pm.np, 0.f);
  const float n_dot_v = n.dot(v);
  if (n_dot_v <= 0) return;
  const float g1v = SmithG1(n_dot_v, alpha) / (4 * n_dot_v);
  for (int l = 0; l < pm.units; ++l) {
    const float g = view.gain[static_cast<size_t>(l)];
    const Eigen::Vector3f& w = view.direction[static_cast<size_t>(l)];
    const float n_dot_w = n.dot(w);
    if (g == 0 || n_dot_w <= 0) continue;
    const Eigen::Vector3f h = (w + v).normalized();
    const float s = g * GgxDistribution(n.dot(h), alpha) * SmithG1(n_dot_w, alpha) * g1v;
    const float* pw = &pm.parallel[static_cast<size_t>(l) * pm.np];
    for (int p = 0; p < pm.np; ++p) m[p] += pw[p] * s;
  }
}

float* Work(PhotometricMaps* m, WorkSlot slot) {
  const size_t n = static_cast<size_t>(m->width) * m->height;
  if (m->work.size() != n * kSlots) m->work.resize(n * kSlots);
  return m->work.data() + n * static_cast<size_t>(slot);
}

void PrepareMaps(int width, int height, PhotometricMaps* m) {
  m->width = width;
  m->height = height;
  for (auto [image, channels] : std::initializer_list<std::pair<Image*, int>>{{&m->diffuse_normal_world, 3},
                                                                              {&m->diffuse_normal_camera, 3},
                                                                              {&m->albedo, 3},
                                                                              {&m->specular_normal_world, 3},
                                                                              {&m->specular_normal_camera, 3},
                                                                              {&m->specular_normal_raw, 3},
                                                                              {&m->specular, 1},
                                                                              {&m->roughness, 1},
                                                                              {&m->specular_sigma, 1},
                                                                              {&m->confidence, 1},
                                                                              {&m->fit_residual, 1}}) {
    image->width = width;
    image->height = height;
    image->channels = channels;
    image->pixels.resize(static_cast<size_t>(width) * height * channels);
  }
  m->flags.resize(static_cast<size_t>(width) * height);
}

namespace {

constexpr int kWindowLanes = 16;

// A row of what the specular regularization reads, planar and padded by the window's radius either side (with no
// lobe there): whether a pixel has a lobe, its diffuse normal, the departure of its raw specular normal from it, log
// roughness, the inverse variances of both (as the filter weights them) and the variances.
struct WindowRow {
  enum Plane { kLobe, kNx, kNy, kNz, kDx, kDy, kDz, kLogAlpha, kInvVarN, kInvVarLa, kVarN, kVarLa, kPlanes };
  std::vector<float> planes;
  size_t stride = 0;
  bool any = false;            // a lobe in the row
  std::vector<uint8_t> lanes;  // per run of kWindowLanes pixels: a lobe in it
  const float* operator[](Plane p) const { return &planes[p * stride]; }
  float* operator[](Plane p) { return &planes[p * stride]; }
};

// The window sums of the 16 pixels of `mid` from column xb (padded index xb + r) that have center[l] set, over
// `rows` (the window's rows in the image, top to bottom): a neighbour left out adds 0, which leaves a sum's bits as
// they were, so that each pixel's sums are those of a loop over its own window.
struct WindowSums {
  float wn[kWindowLanes], wl[kWindowLanes], mn[3][kWindowLanes], ml[kWindowLanes], sn[3][kWindowLanes],
      sl[kWindowLanes], qn[kWindowLanes], ql[kWindowLanes], nn[kWindowLanes], nl[kWindowLanes], count[kWindowLanes];
};

__attribute__((always_inline)) inline void WindowSums16Impl(const WindowRow* const* rows, int n_rows,
                                                            const WindowRow& mid, int xb, int r, const bool* center,
                                                            WindowSums* out) {
  constexpr int kL = kWindowLanes;
  using P = WindowRow::Plane;
  float n0[3][kL], on[kL];
  for (int l = 0; l < kL; ++l) {
    const size_t o = static_cast<size_t>(xb + r + l);
    n0[0][l] = mid[P::kNx][o];
    n0[1][l] = mid[P::kNy][o];
    n0[2][l] = mid[P::kNz][o];
    on[l] = center[l] ? 1.f : 0.f;
  }
  float wn[kL] = {}, wl[kL] = {}, mn[3][kL] = {}, ml[kL] = {}, sn[3][kL] = {}, sl[kL] = {}, qn[kL] = {}, ql[kL] = {},
        nn[kL] = {}, nl[kL] = {}, count[kL] = {};
  for (int k = 0; k < n_rows; ++k) {
    const WindowRow& row = *rows[k];
    for (int dx = -r; dx <= r; ++dx) {
      const size_t o = static_cast<size_t>(xb + r + dx);
      const float* lobe = row[P::kLobe] + o;
      const float* nx = row[P::kNx] + o;
      const float* ny = row[P::kNy] + o;
      const float* nz = row[P::kNz] + o;
      const float* d[3] = {row[P::kDx] + o, row[P::kDy] + o, row[P::kDz] + o};
      const float* la = row[P::kLogAlpha] + o;
      const float* ia = row[P::kInvVarN] + o;
      const float* ib = row[P::kInvVarLa] + o;
      const float* vn = row[P::kVarN] + o;
      const float* vl = row[P::kVarLa] + o;
      for (int l = 0; l < kL; ++l) {
        const bool take = on[l] * lobe[l] > 0 && !(n0[0][l] * nx[l] + n0[1][l] * ny[l] + n0[2][l] * nz[l] <= 0.866f);
        for (int c = 0; c < 3; ++c) {
          const float v = d[c][l];
          mn[c][l] += take ? ia[l] * v : 0.f;
          sn[c][l] += take ? v : 0.f;
          qn[l] += take ? v * v : 0.f;
        }
        wn[l] += take ? ia[l] : 0.f;
        nn[l] += take ? vn[l] : 0.f;
        ml[l] += take ? ib[l] * la[l] : 0.f;
        sl[l] += take ? la[l] : 0.f;
        ql[l] += take ? la[l] * la[l] : 0.f;
        wl[l] += take ? ib[l] : 0.f;
        nl[l] += take ? vl[l] : 0.f;
        count[l] += take ? 1.f : 0.f;
      }
    }
  }
  std::copy_n(wn, kL, out->wn);
  std::copy_n(wl, kL, out->wl);
  std::copy_n(ml, kL, out->ml);
  std::copy_n(sl, kL, out->sl);
  std::copy_n(qn, kL, out->qn);
  std::copy_n(ql, kL, out->ql);
  std::copy_n(nn, kL, out->nn);
  std::copy_n(nl, kL, out->nl);
  std::copy_n(count, kL, out->count);
  for (int c = 0; c < 3; ++c) {
    std::copy_n(mn[c], kL, out->mn[c]);
    std::copy_n(sn[c], kL, out->sn[c]);
  }
}

#if STAGE_X86_64
// The same in AVX-512 lanes: the same operations in the same order per lane (the file is compiled without
// contraction of multiply and add), so the same bits.
__attribute__((target("avx512f,avx512dq"))) void WindowSums16Avx512(const WindowRow* const* rows, int n_rows,
                                                                    const WindowRow& mid, int xb, int r,
                                                                    const bool* center, WindowSums* out) {
  using P = WindowRow::Plane;
  const size_t c0 = static_cast<size_t>(xb + r);
  const __m512 n0x = _mm512_loadu_ps(mid[P::kNx] + c0), n0y = _mm512_loadu_ps(mid[P::kNy] + c0),
               n0z = _mm512_loadu_ps(mid[P::kNz] + c0);
  __mmask16 on = 0;
  for (int l = 0; l < kWindowLanes; ++l) on |= center[l] ? static_cast<__mmask16>(1u << l) : 0;
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f), edge = _mm512_set1_ps(0.866f);
  __m512 wn = zero, wl = zero, mn[3] = {zero, zero, zero}, ml = zero, sn[3] = {zero, zero, zero}, sl = zero, qn = zero,
         ql = zero, nn = zero, nl = zero, count = zero;
  for (int k = 0; k < n_rows; ++k) {
    const WindowRow& row = *rows[k];
    for (int dx = -r; dx <= r; ++dx) {
      const size_t o = static_cast<size_t>(xb + r + dx);
      const __m512 dot = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(n0x, _mm512_loadu_ps(row[P::kNx] + o)),
                                                     _mm512_mul_ps(n0y, _mm512_loadu_ps(row[P::kNy] + o))),
                                       _mm512_mul_ps(n0z, _mm512_loadu_ps(row[P::kNz] + o)));
      const __mmask16 take = _mm512_mask_cmp_ps_mask(on, _mm512_loadu_ps(row[P::kLobe] + o), zero, _CMP_GT_OQ) &
                             _mm512_cmp_ps_mask(dot, edge, _CMP_NLE_UQ);
      if (take == 0) continue;  // adds nothing
      const __m512 ia = _mm512_loadu_ps(row[P::kInvVarN] + o), ib = _mm512_loadu_ps(row[P::kInvVarLa] + o);
      const P planes[3] = {P::kDx, P::kDy, P::kDz};
      for (int c = 0; c < 3; ++c) {
        const __m512 v = _mm512_loadu_ps(row[planes[c]] + o);
        mn[c] = _mm512_mask_add_ps(mn[c], take, mn[c], _mm512_mul_ps(ia, v));
        sn[c] = _mm512_mask_add_ps(sn[c], take, sn[c], v);
        qn = _mm512_mask_add_ps(qn, take, qn, _mm512_mul_ps(v, v));
      }
      const __m512 la = _mm512_loadu_ps(row[P::kLogAlpha] + o);
      wn = _mm512_mask_add_ps(wn, take, wn, ia);
      nn = _mm512_mask_add_ps(nn, take, nn, _mm512_loadu_ps(row[P::kVarN] + o));
      ml = _mm512_mask_add_ps(ml, take, ml, _mm512_mul_ps(ib, la));
      sl = _mm512_mask_add_ps(sl, take, sl, la);
      ql = _mm512_mask_add_ps(ql, take, ql, _mm512_mul_ps(la, la));
      wl = _mm512_mask_add_ps(wl, take, wl, ib);
      nl = _mm512_mask_add_ps(nl, take, nl, _mm512_loadu_ps(row[P::kVarLa] + o));
      count = _mm512_mask_add_ps(count, take, count, one);
    }
  }
  _mm512_storeu_ps(out->wn, wn);
  _mm512_storeu_ps(out->wl, wl);
  _mm512_storeu_ps(out->ml, ml);
  _mm512_storeu_ps(out->sl, sl);
  _mm512_storeu_ps(out->qn, qn);
  _mm512_storeu_ps(out->ql, ql);
  _mm512_storeu_ps(out->nn, nn);
  _mm512_storeu_ps(out->nl, nl);
  _mm512_storeu_ps(out->count, count);
  for (int c = 0; c < 3; ++c) {
    _mm512_storeu_ps(out->mn[c], mn[c]);
    _mm512_storeu_ps(out->sn[c], sn[c]);
  }
}
#endif  // STAGE_X86_64

void WindowSums16(const WindowRow* const* rows, int n_rows, const WindowRow& mid, int xb, int r, const bool* center,
                  WindowSums* out) {
#if STAGE_X86_64
  if (FastVectorKernels() && FastVectorKernelsAvailable()) {
    WindowSums16Avx512(rows, n_rows, mid, xb, r, center, out);
    return;
  }
#endif
  WindowSums16Impl(rows, n_rows, mid, xb, r, center, out);
}

}  // namespace

// A local Wiener (Lee) filter of the departure of the specular normal from the diffuse one (3 components) and of log
// roughness, each with its own per-pixel noise: in a (2r+1)^2 window of the pixels with a lobe on the same side of an
// edge, the inverse-variance weighted mean mu and the spread s^2 about it; the pixel keeps mu + k (x - mu) with
// k = signal / (signal + noise), signal = max(0, s^2 - mean noise). Each thread keeps the window's rows in a ring,
// planar (WindowRow), from band to band, and sums 16 pixels' windows at a time.
void RegularizeSpecular(int radius, int threads, const Eigen::Matrix3f& to_camera, PhotometricMaps* maps) {
  PhotometricMaps& m = *maps;
  const int w = m.width, h = m.height;
  // A window wider than the image holds the whole image, as one of the image's size does.
  const int r = std::clamp(radius, 0, std::max(w, h));
  const float* var_n = Work(&m, kVarNormal);
  const float* var_la = Work(&m, kVarLogAlpha);
  const float* nd = m.diffuse_normal_world.pixels.data();
  const float* raw = m.specular_normal_raw.pixels.data();
  auto has_lobe = [&](size_t i) { return (m.flags[i] & (kLowSignal | kNoSpecular)) == 0; };
  // The roughness map is both read (the raw fits) and written (regularized): the rows within the radius of a band's
  // ends, which the bands beside it read, are written when every band is done.
  std::vector<std::vector<float>> deferred(static_cast<size_t>(h));
  ParallelRows(h, threads, [&](int y0, int y1) {
    using P = WindowRow::Plane;
    const size_t stride = static_cast<size_t>(w) + 2 * r + kWindowLanes;  // room for a last batch past the edge
    // Kept from band to band: only the lobe plane's padding must stay 0 (fill() writes the rest of what is read).
    static thread_local std::vector<WindowRow> ring;
    if (ring.size() != static_cast<size_t>(2 * r + 1) || ring[0].stride != stride) {
      ring.assign(static_cast<size_t>(2 * r + 1), WindowRow{});
      for (WindowRow& row : ring) {
        row.stride = stride;
        row.planes.assign(P::kPlanes * stride, 0.f);
        row.lanes.assign(static_cast<size_t>(w + kWindowLanes - 1) / kWindowLanes, 0);
      }
    }
    auto slot = [&](int yy) -> WindowRow& { return ring[static_cast<size_t>(yy % (2 * r + 1))]; };
    // Row yy of the image into its slot of the ring: where a lobe is, and the rest only in the runs of kWindowLanes
    // pixels that have one (where there is none, nothing else is read).
    auto fill = [&](int yy) {
      WindowRow& row = slot(yy);
      const size_t r0 = static_cast<size_t>(yy) * w;
      float* lobe = row[P::kLobe] + r;
      row.any = false;
      for (int xb = 0; xb < w; xb += kWindowLanes) {
        const int n = std::min(kWindowLanes, w - xb);
        bool any = false;
        for (int x = xb; x < xb + n; ++x) {
          lobe[x] = has_lobe(r0 + x) ? 1.f : 0.f;
          any |= lobe[x] > 0;
        }
        row.lanes[static_cast<size_t>(xb / kWindowLanes)] = any;
        row.any |= any;
        if (!any) continue;
        for (int c = 0; c < 3; ++c) {
          float* nc = row[static_cast<P>(P::kNx + c)] + r;
          float* dc = row[static_cast<P>(P::kDx + c)] + r;
          for (int x = xb; x < xb + n; ++x) {
            const size_t i = 3 * (r0 + x) + c;
            nc[x] = nd[i];
            dc[x] = raw[i] - nd[i];
          }
        }
        float* ia = row[P::kInvVarN] + r;
        float* ib = row[P::kInvVarLa] + r;
        float* vn = row[P::kVarN] + r;
        float* vl = row[P::kVarLa] + r;
        float* la = row[P::kLogAlpha] + r;
        for (int x = xb; x < xb + n; ++x) {
          vn[x] = var_n[r0 + x];
          vl[x] = var_la[r0 + x];
          ia[x] = 1 / std::max(1e-12f, vn[x]);
          ib[x] = 1 / std::max(1e-12f, vl[x]);
          la[x] = lobe[x] > 0 ? PortableLog(m.roughness.pixels[r0 + x]) : 0.f;
        }
      }
    };
    for (int yy = std::max(0, y0 - r); yy < std::min(h, y0 + r); ++yy) fill(yy);
    std::vector<const WindowRow*> rows(ring.size());
    for (int y = y0; y < y1; ++y) {
      if (y + r < h) fill(y + r);
      int n_rows = 0;
      for (int yy = std::max(0, y - r); yy <= std::min(h - 1, y + r); ++yy) rows[n_rows++] = &slot(yy);
      const WindowRow& mid = slot(y);
      const size_t row0 = static_cast<size_t>(y) * w;
      float* roughness = m.roughness.pixels.data() + row0;
      if (y < y0 + r || y >= y1 - r) {
        deferred[static_cast<size_t>(y)].assign(roughness, roughness + w);
        roughness = deferred[static_cast<size_t>(y)].data();
      }
      for (int xb = 0; xb < w; xb += kWindowLanes) {
        if (xb % kStreamRun == 0) {  // a run without a lobe: zeros straight to memory
          const int n = std::min(kStreamRun, w - xb);
          bool any = false;
          for (int k = 0; k < n && mid.any; k += kWindowLanes) {
            any |= mid.lanes[static_cast<size_t>((xb + k) / kWindowLanes)] != 0;
          }
          if (!any) {
            StreamZeros(&m.specular_normal_world.pixels[3 * (row0 + xb)], 3 * static_cast<size_t>(n));
            StreamZeros(&m.specular_normal_camera.pixels[3 * (row0 + xb)], 3 * static_cast<size_t>(n));
            xb += n - kWindowLanes;
            continue;
          }
        }
        const int lanes = std::min(kWindowLanes, w - xb);
        bool center[kWindowLanes];
        const bool any = mid.lanes[static_cast<size_t>(xb / kWindowLanes)];
        for (int l = 0; l < kWindowLanes; ++l) center[l] = any && l < lanes && mid[P::kLobe][r + xb + l] > 0;
        WindowSums sums;
        if (any && r > 0) WindowSums16(rows.data(), n_rows, mid, xb, r, center, &sums);
        for (int l = 0; l < lanes; ++l) {
          const size_t i = row0 + xb + l;
          float* sw = &m.specular_normal_world.pixels[3 * i];
          float* sc = &m.specular_normal_camera.pixels[3 * i];
          if (!center[l]) {
            std::fill(sw, sw + 3, 0.f);
            std::fill(sc, sc + 3, 0.f);
            continue;
          }
          const size_t o = static_cast<size_t>(r + xb + l);
          const float* n0 = &nd[3 * i];
          float dn[3] = {mid[P::kDx][o], mid[P::kDy][o], mid[P::kDz][o]};
          float la = mid[P::kLogAlpha][o];
          const float count = r > 0 ? sums.count[l] : 0.f;
          if (count >= 3) {
            const float inv = 1.f / count;
            float spread = sums.qn[l] * inv;
            float mn[3];
            for (int c = 0; c < 3; ++c) {
              mn[c] = sums.mn[c][l] / sums.wn[l];
              spread += mn[c] * mn[c] - 2 * mn[c] * sums.sn[c][l] * inv;
            }
            const float signal = std::max(0.f, spread - sums.nn[l] * inv);
            const float k = signal / (signal + std::max(1e-12f, var_n[i]));
            for (int c = 0; c < 3; ++c) dn[c] = mn[c] + k * (dn[c] - mn[c]);
            const float ml = sums.ml[l] / sums.wl[l];
            const float spread_l = sums.ql[l] * inv + ml * ml - 2 * ml * sums.sl[l] * inv;
            const float signal_l = std::max(0.f, spread_l - sums.nl[l] * inv);
            const float kl = signal_l / (signal_l + std::max(1e-12f, var_la[i]));
            la = ml + kl * (la - ml);
          }
          const Eigen::Vector3f ns = Eigen::Vector3f(n0[0] + dn[0], n0[1] + dn[1], n0[2] + dn[2]).normalized();
          const Eigen::Vector3f nc = to_camera * ns;
          std::copy(ns.data(), ns.data() + 3, sw);
          std::copy(nc.data(), nc.data() + 3, sc);
          roughness[xb + l] = PortableExp(la);
        }
      }
    }
    StreamFence();
  });
  for (int y = 0; y < h; ++y) {
    const std::vector<float>& row = deferred[static_cast<size_t>(y)];
    if (!row.empty()) std::copy(row.begin(), row.end(), &m.roughness.pixels[static_cast<size_t>(y) * w]);
  }
}

}  // namespace internal

namespace {

using internal::DiffuseFromView;
using internal::kPi;
using internal::MakePatternMatrix;
using internal::PairPatterns;
using internal::ParallelRows;
using internal::PatternMatrix;
using internal::SpecularFromView;
using internal::Twins;

struct SpecularFit {
  Eigen::Vector3f n = Eigen::Vector3f::Zero();
  float alpha = 0, rho = 0;
  float var_n = 0;          // variance of the normal's direction, rad^2 (both tangent axes)
  float var_log_alpha = 0;  // of log(alpha)
  float var_rho = 0;        // of rho
  float chi2 = 0;           // reduced
  bool converged = false;   // a fit was made (rho may be 0: no lobe)
  bool ok = false;          // and found a lobe
};

constexpr float kMinAlpha = internal::kMinLobeAlpha, kMaxAlpha = 1.5f;
// The smallest eigenvalue of a lobe fit's information (its parameters scaled to unit information each), relative to its
// largest, below which the fit's parameters are not determined (its variances infinite): the Jacobian's finite
// differences of float images (steps of 2e-3) carry about 5e-5 of each column's scale, so a singular value under that
// share of the largest (eigenvalues under ~3e-9) is theirs.
constexpr double kMinInformationRatio = 1e-8;

// A frame of the plane tangent to unit n: the normal is moved as n + a t1 + b t2, normalized.
void TangentFrame(const Eigen::Vector3f& n, Eigen::Vector3f* t1, Eigen::Vector3f* t2) {
  *t1 = (std::abs(n.x()) < 0.9f ? Eigen::Vector3f::UnitX() : Eigen::Vector3f::UnitY()).cross(n).normalized();
  *t2 = n.cross(*t1);
}

// The finite-difference steps of the lobe's parameters: tangent offsets of the normal, log alpha.
constexpr float kStep[3] = {2e-3f, 2e-3f, 1e-2f};

// A lobe fit's variances from `j4`, the weighted residuals' Jacobian over (tangent offsets a, b of the normal; log
// alpha; rho). In double, through the eigenvalues of the information with each parameter scaled to unit information
// (so that the test does not depend on the parameters' units, nor on the lobe's intensity, which scales the first three
// columns): where the images barely depend on a combination of the parameters (a lobe that one unit or none sees,
// a roughness the intensity trades off exactly) the information is near singular, and a float inverse of it had
// come out with variances of zero (clamped from negative): the worst fits passed as the most precise, and weighed
// most in the regularization. Such a fit has no finite variance.
void SetLobeVariances(const Eigen::MatrixXf& j4, SpecularFit* fit) {
  const Eigen::MatrixXd jd = j4.cast<double>();
  const Eigen::Matrix4d info = jd.transpose() * jd;
  const Eigen::Vector4d unit = info.diagonal().cwiseMax(1e-300).cwiseSqrt().cwiseInverse();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eig(unit.asDiagonal() * info * unit.asDiagonal());
  const Eigen::Vector4d lambdas = eig.eigenvalues();  // ascending
  if (eig.info() != Eigen::Success || !lambdas.allFinite() || !(info.diagonal().minCoeff() > 0) ||
      lambdas[0] <= kMinInformationRatio * lambdas[3]) {
    fit->var_n = fit->var_log_alpha = fit->var_rho = 1e30f;
  } else {
    const Eigen::Matrix4d cov = unit.asDiagonal() * eig.eigenvectors() * lambdas.cwiseInverse().asDiagonal() *
                                eig.eigenvectors().transpose() * unit.asDiagonal();
    fit->var_n = static_cast<float>(cov(0, 0) + cov(1, 1));
    fit->var_log_alpha = static_cast<float>(cov(2, 2));
    fit->var_rho = static_cast<float>(cov(3, 3));
  }
}

// Noise-weighted least squares of the specular images `s` (weights `wt`) over normal, roughness and intensity
// (intensity in closed form for each normal and roughness), Levenberg-Marquardt from the best of the `starts`.
SpecularFit FitSpecular(const UnitView& view, const PatternMatrix& pm, const float* s, const float* wt,
                        const Eigen::Vector3f& v, const std::vector<Eigen::Vector3f>& starts, float scale) {
  const int np = pm.np;
  std::vector<float> m(static_cast<size_t>(np));
  // Cost and intensity of (n, alpha); residuals into r when given.
  auto evaluate = [&](const Eigen::Vector3f& n, float alpha, float* rho, float* r) {
    SpecularFromView(view, pm, n, v, alpha, m.data());
    double smm = 0, ssm = 0;
    for (int p = 0; p < np; ++p) {
      m[static_cast<size_t>(p)] *= scale;
      smm += wt[p] * m[static_cast<size_t>(p)] * m[static_cast<size_t>(p)];
      ssm += wt[p] * s[p] * m[static_cast<size_t>(p)];
    }
    *rho = smm > 0 ? static_cast<float>(std::max(0.0, ssm / smm)) : 0.f;
    double cost = 0;
    for (int p = 0; p < np; ++p) {
      const float e = std::sqrt(wt[p]) * (s[p] - *rho * m[static_cast<size_t>(p)]);
      if (r != nullptr) r[p] = e;
      cost += static_cast<double>(e) * e;
    }
    return smm > 0 ? cost : 1e300;
  };
  SpecularFit fit;
  double best = 1e300;
  Eigen::Vector3f n;
  float alpha = 0.3f, rho = 0;
  for (const Eigen::Vector3f& start : starts) {
    if (start.dot(v) <= 0.02f) continue;
    for (float a : {0.12f, 0.25f, 0.45f}) {
      float r0;
      const double c = evaluate(start, a, &r0, nullptr);
      if (c < best) {
        best = c;
        n = start;
        alpha = a;
      }
    }
  }
  if (best >= 1e300) return fit;
  // Levenberg-Marquardt over (tangent offsets a, b of the normal; log alpha).
  std::vector<float> r(static_cast<size_t>(np)), r1(static_cast<size_t>(np));
  Eigen::MatrixXf jac(np, 3);
  float lambda = 1e-2f;
  double cost = evaluate(n, alpha, &rho, r.data());
  Eigen::Matrix3f jtj = Eigen::Matrix3f::Identity();
  Eigen::Vector3f t1, t2;
  // (n, alpha) moved by d in (t1, t2, log alpha); the fit keeps alpha in its range, the covariance does not.
  auto step = [&](const Eigen::Vector3f& d, bool clamp, Eigen::Vector3f* n_out, float* a_out) {
    *n_out = (n + d[0] * t1 + d[1] * t2).normalized();
    *a_out = alpha * internal::PortableExp(d[2]);
    if (clamp) *a_out = std::clamp(*a_out, kMinAlpha, kMaxAlpha);
  };
  for (int it = 0; it < 40; ++it) {
    TangentFrame(n, &t1, &t2);
    for (int k = 0; k < 3; ++k) {
      Eigen::Vector3f d = Eigen::Vector3f::Zero();
      d[k] = kStep[k];
      Eigen::Vector3f nk;
      float ak, rk;
      step(d, /*clamp=*/true, &nk, &ak);
      evaluate(nk, ak, &rk, r1.data());
      for (int p = 0; p < np; ++p) jac(p, k) = (r1[static_cast<size_t>(p)] - r[static_cast<size_t>(p)]) / kStep[k];
    }
    const Eigen::Map<const Eigen::VectorXf> rv(r.data(), np);
    jtj = jac.transpose() * jac;
    const Eigen::Vector3f g = jac.transpose() * rv;
    bool improved = false;
    for (int tries = 0; tries < 6 && !improved; ++tries) {
      Eigen::Matrix3f a = jtj;
      for (int k = 0; k < 3; ++k) a(k, k) += lambda * (jtj(k, k) + 1e-6f);
      const Eigen::Vector3f d = -a.ldlt().solve(g);
      if (!d.allFinite()) break;
      // Keep steps small enough for the tangent-plane parameterization.
      const Eigen::Vector3f dd(std::clamp(d[0], -0.3f, 0.3f), std::clamp(d[1], -0.3f, 0.3f),
                               std::clamp(d[2], -1.f, 1.f));
      Eigen::Vector3f nn;
      float na, nrho;
      step(dd, /*clamp=*/true, &nn, &na);
      const double c = evaluate(nn, na, &nrho, r1.data());
      if (c < cost) {
        improved = true;
        const bool converged = dd.head<2>().norm() < 2e-4f && std::abs(dd[2]) < 1e-3f;
        n = nn;
        alpha = na;
        rho = nrho;
        cost = c;
        r.swap(r1);
        lambda = std::max(1e-6f, lambda / 4);
        if (converged) it = 1000;
      } else {
        lambda *= 8;
      }
    }
    if (!improved) break;
  }
  fit.n = n;
  fit.alpha = alpha;
  fit.rho = rho;
  fit.chi2 = static_cast<float>(cost / std::max(1, np - 4));
  // Covariance of (tangent offsets a, b; log alpha; rho) from the Jacobian of the residuals at the optimum, rho as a
  // parameter of its own so that its trade-off with alpha shows.
  {
    TangentFrame(n, &t1, &t2);
    Eigen::MatrixXf j4(np, 4);
    std::vector<float> m0(static_cast<size_t>(np));
    SpecularFromView(view, pm, n, v, alpha, m0.data());
    for (int k = 0; k < 3; ++k) {
      Eigen::Vector3f d = Eigen::Vector3f::Zero();
      d[k] = kStep[k];
      Eigen::Vector3f nk;
      float ak;
      step(d, /*clamp=*/false, &nk, &ak);
      SpecularFromView(view, pm, nk, v, ak, m.data());
      for (int p = 0; p < np; ++p) {
        j4(p, k) =
            -std::sqrt(wt[p]) * rho * scale * (m[static_cast<size_t>(p)] - m0[static_cast<size_t>(p)]) / kStep[k];
      }
    }
    for (int p = 0; p < np; ++p) j4(p, 3) = -std::sqrt(wt[p]) * scale * m0[static_cast<size_t>(p)];
    SetLobeVariances(j4, &fit);
  }
  fit.converged = fit.n.allFinite() && std::isfinite(fit.chi2);
  fit.ok = fit.converged && rho > 0;
  return fit;
}

}  // namespace

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) * 180.0 / M_PI;
}

namespace {

std::vector<Eigen::Vector3f> UnitPositions(const LightModel& light) {
  std::vector<Eigen::Vector3f> units;
  for (const Eigen::Vector3d& d : light.directions) units.push_back((d * light.radius_mm).cast<float>());
  return units;
}

// Sets bit l of `bits` for every unit the mesh does not hide from `point`: a shadow ray from `clearance` off the point
// towards the unit (and from `lifted`, the point a micrometre off the face it lands on).
void MarkVisibleUnits(const MeshBvh& mesh, const Eigen::Vector3f& point, const Eigen::Vector3f& lifted,
                      const std::vector<Eigen::Vector3f>& units, float clearance, uint64_t* bits) {
  for (size_t l = 0; l < units.size(); ++l) {
    const Eigen::Vector3f start = lifted + clearance * (units[l] - point).normalized();
    if (mesh.Occluded(start, units[l])) continue;
    bits[l / 64] |= uint64_t{1} << (l % 64);
  }
}

Eigen::Vector3f PixelRay(const PhotometricCamera& camera, const Eigen::Vector3f& origin, size_t i) {
  return camera.rays.empty() ? Eigen::Vector3f(-origin.normalized()) : camera.rays[i];
}

// Places each of `pixels` at its `distance` along its ray and traces its shadows in `mesh` from there.
void PlaceAlongRays(const MeshBvh& mesh, const PhotometricCamera& camera, const LightModel& light,
                    const PhotometricOptions& options, const std::vector<size_t>& pixels,
                    const std::vector<float>& distance, PixelGeometry* g) {
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  const std::vector<Eigen::Vector3f> units = UnitPositions(light);
  const float clearance = static_cast<float>(options.shadow_clearance_mm);
  ParallelRows(static_cast<int>(pixels.size()), options.threads, [&](int k0, int k1) {
    for (int k = k0; k < k1; ++k) {
      const size_t i = pixels[static_cast<size_t>(k)];
      const Eigen::Vector3f point = origin + distance[i] * PixelRay(camera, origin, i);
      std::copy(point.data(), point.data() + 3, &g->points[3 * i]);
      uint64_t* bits = &g->visible[i * static_cast<size_t>(g->words)];
      std::fill(bits, bits + g->words, 0);
      MarkVisibleUnits(mesh, point, point, units, clearance, bits);
    }
  });
}

}  // namespace

PixelGeometry TraceGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, int width, int height,
                            const LightModel& light, double clearance_mm, int threads) {
  PixelGeometry g;
  g.width = width;
  g.height = height;
  g.words = (light.units() + 63) / 64;
  const size_t pixels = static_cast<size_t>(width) * height;
  g.points.assign(3 * pixels, std::nanf(""));
  g.visible.assign(pixels * static_cast<size_t>(g.words), 0);
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  // Every ray to its nearest facet, and which side of it it meets.
  std::vector<Eigen::Vector3f> lifted(pixels);
  std::vector<int8_t> side(pixels, 0);  // +1: the facet's front (its vertices counter-clockwise), -1: its back
  ParallelRows(height, threads, [&](int y0, int y1) {
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < width; ++x) {
        const size_t i = static_cast<size_t>(y) * width + x;
        const Eigen::Vector3f dir = PixelRay(camera, origin, i);
        MeshHit hit;
        if (!mesh.Nearest(origin, dir, INFINITY, &hit)) continue;
        const auto& t = mesh.mesh().triangles[static_cast<size_t>(hit.triangle)];
        const Eigen::Vector3f& p0 = mesh.mesh().positions[static_cast<size_t>(t[0])];
        Eigen::Vector3f face = (mesh.mesh().positions[static_cast<size_t>(t[1])] - p0)
                                   .cross(mesh.mesh().positions[static_cast<size_t>(t[2])] - p0)
                                   .normalized();
        side[i] = face.dot(dir) > 0 ? -1 : 1;
        if (side[i] < 0) face = -face;
        const Eigen::Vector3f point = origin + hit.t * dir;
        std::copy(point.data(), point.data() + 3, &g.points[3 * i]);
        lifted[i] = point + 1e-3f * face;  // a micrometre off the face it lands on
      }
    }
  });
  // The side most rays meet is the surface's outside (a mesh may wind either way); a ray meeting the inside came
  // through a hole in the surface (a reconstruction's: onto the inside of the far side of the head), and its pixel is
  // left to FillGeometry.
  int64_t front = 0, back = 0;
  for (int8_t v : side) (v > 0 ? front : back) += v != 0;
  const int8_t outside = front >= back ? 1 : -1;
  const float clearance = static_cast<float>(clearance_mm);
  const std::vector<Eigen::Vector3f> units = UnitPositions(light);
  ParallelRows(height, threads, [&](int y0, int y1) {
    for (size_t i = static_cast<size_t>(y0) * width; i < static_cast<size_t>(y1) * width; ++i) {
      if (side[i] == 0) continue;
      if (side[i] != outside) {
        std::fill(&g.points[3 * i], &g.points[3 * i] + 3, std::nanf(""));
        continue;
      }
      const Eigen::Vector3f point = Eigen::Map<const Eigen::Vector3f>(&g.points[3 * i]);
      MarkVisibleUnits(mesh, point, lifted[i], units, clearance, &g.visible[i * static_cast<size_t>(g.words)]);
    }
  });
  return g;
}

namespace {

// How far about a placed pixel's first distance its ray is searched for the visual hull, and the search's step, mm: the
// neighbours' distance lands up to a few centimetres off (docs/geometry.md); a step under the hull's thinnest stretch
// a grazing ray crosses near the mesh's edge.
constexpr double kHullSearchMm = 100;
constexpr double kHullStepMm = 1;

// The stretch of each of `pixels`' rays (the placed ones) inside `hull` about its distance, cut to `depth_mm` past the
// hull's entry (g->hull_in, hull_out; NaN: missed), and each distance moved into it.
void BoundByHull(const VisualHull& hull, const PhotometricCamera& camera, const std::vector<size_t>& pixels,
                 double depth_mm, int threads, std::vector<float>* distance, PixelGeometry* g) {
  const size_t n = static_cast<size_t>(g->width) * g->height;
  g->hull_in.assign(n, std::nanf(""));
  g->hull_out.assign(n, std::nanf(""));
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  ParallelRows(static_cast<int>(pixels.size()), threads, [&](int k0, int k1) {
    for (int k = k0; k < k1; ++k) {
      const size_t i = pixels[static_cast<size_t>(k)];
      const double d = (*distance)[i];
      const Eigen::Vector3d from = origin.cast<double>(), ray = PixelRay(camera, origin, i).cast<double>();
      double t0 = std::max(0.0, d - kHullSearchMm), in = 0, out = 0;
      bool entered = false;
      if (!hull.FirstSpan(from, ray, t0, d + kHullSearchMm, kHullStepMm, &in, &out, &entered)) continue;
      // Inside the hull where the search began (the neighbours' distance lies over 100 mm behind the skin, as on a
      // ray that passes a chin onto the neck): searched again from nearer the camera, to where the ray enters.
      for (int again = 0; again < 3 && !entered && in == t0 && t0 > 0; ++again) {
        t0 = std::max(0.0, t0 - 2 * kHullSearchMm);
        if (!hull.FirstSpan(from, ray, t0, d + kHullSearchMm, kHullStepMm, &in, &out, &entered)) break;
      }
      g->hull_in[i] = static_cast<float>(in);
      // The depth is counted from where the ray enters the hull, not from where the search began.
      g->hull_out[i] = static_cast<float>(entered ? std::min(out, in + depth_mm) : out);
      (*distance)[i] = std::clamp((*distance)[i], g->hull_in[i], g->hull_out[i]);
    }
  });
}

// `d` kept within pixel i's stretch of the visual hull, where it has one.
float WithinHull(const PixelGeometry& g, size_t i, float d) {
  if (g.hull_in.empty() || g.hull_in[i] != g.hull_in[i] || d != d) return d;
  return std::clamp(d, g.hull_in[i], g.hull_out[i]);
}

}  // namespace

absl::StatusOr<int64_t> FillGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, const LightModel& light,
                                     const std::vector<Image>& frames, const PhotometricOptions& options,
                                     PixelGeometry* g, const VisualHull* hull) {
  g->hull_in.clear();
  g->hull_out.clear();
  if (options.geometry_fill_px <= 0) return 0;
  auto twins = internal::PairPatterns(light);
  if (!twins.ok()) return twins.status();
  const size_t full = static_cast<size_t>(twins->cross[static_cast<size_t>(twins->full)]);
  if (frames.size() != light.patterns.size() || frames[full].width != g->width || frames[full].height != g->height ||
      frames[full].channels != 3) {
    return absl::InvalidArgumentError("geometry fill: the images do not match the patterns or the geometry");
  }
  // Only pixels bright enough to be solved are placed (half the solver's bar: the leakage correction moves it a
  // little).
  const float lit = static_cast<float>(internal::MinSignalDn(options, camera) / 2);
  const int w = g->width, h = g->height;
  const size_t pixels = static_cast<size_t>(w) * h;
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  // Each covered pixel's distance along its ray, spread to the missing pixels about them.
  std::vector<float> depth(pixels, std::nanf(""));
  for (size_t i = 0; i < pixels; ++i) {
    if (!g->Covers(i)) continue;
    depth[i] = (Eigen::Map<const Eigen::Vector3f>(&g->points[3 * i]) - origin).dot(PixelRay(camera, origin, i));
  }
  GrowIntoGaps(w, h, /*channels=*/1, options.geometry_fill_px, GapGrowth::kMean, &depth);
  std::vector<size_t> filled;
  for (size_t i = 0; i < pixels; ++i) {
    if (g->Covers(i) || depth[i] != depth[i]) continue;
    const float* v = &frames[full].pixels[3 * i];
    if (v[0] + v[1] + v[2] >= lit) filled.push_back(i);
  }
  g->placed.assign(pixels, 0);
  for (size_t i : filled) g->placed[i] = 1;
  if (hull != nullptr && !hull->empty() && options.geometry_hull) {
    BoundByHull(*hull, camera, filled, options.geometry_hull_depth_mm, options.threads, &depth, g);
  }
  PlaceAlongRays(mesh, camera, light, options, filled, depth, g);
  return static_cast<int64_t>(filled.size());
}

namespace {

// Where pixel i's ray meets the planes of its set 8-neighbours (each through the neighbour's point, across the mean of
// its and the pixel's normal), the mean distance along the ray over those that face the ray by more than a grazing
// angle. Planes of neighbours whose normal agrees with the pixel's (within kAgree) are taken alone when there are any
// (`agreed`): across a fold or a jump in depth (a chin over the neck) the normals disagree. Without a facing plane, the
// neighbours' mean distance. `distance`: NaN where not set. `normals`: the solved normals, 0 where not solved.
struct PlaneMeet {
  float distance = std::nanf("");
  bool agreed = false;
};
PlaneMeet DistanceOnNeighbourPlanes(const PhotometricCamera& camera, const Eigen::Vector3f& origin,
                                    const PixelGeometry& g, const std::vector<float>& distance, const Image& normals,
                                    int x, int y) {
  constexpr float kMinFacing = 0.1f;  // cos of the normal to the ray: grazing planes say little about the distance
  constexpr float kAgree = 0.866f;    // cos 30 degrees
  const size_t i = static_cast<size_t>(y) * g.width + x;
  const Eigen::Vector3f ray = PixelRay(camera, origin, i);
  const Eigen::Vector3f own = Eigen::Map<const Eigen::Vector3f>(&normals.pixels[3 * i]);
  const bool solved = own.squaredNorm() > 0;
  float on_planes[2] = {0, 0}, flat = 0;  // [0]: every facing plane, [1]: those agreeing with the pixel's normal
  int planes[2] = {0, 0}, neighbours = 0;
  for (int dy = -1; dy <= 1; ++dy) {
    for (int dx = -1; dx <= 1; ++dx) {
      const int nx = x + dx, ny = y + dy;
      if ((dx == 0 && dy == 0) || nx < 0 || ny < 0 || nx >= g.width || ny >= g.height) continue;
      const size_t n = static_cast<size_t>(ny) * g.width + nx;
      if (distance[n] != distance[n]) continue;
      flat += distance[n];
      ++neighbours;
      const Eigen::Vector3f theirs = Eigen::Map<const Eigen::Vector3f>(&normals.pixels[3 * n]);
      if (!(theirs.squaredNorm() > 0)) continue;  // not solved (or not finite)
      const Eigen::Vector3f normal = (solved ? own + theirs : theirs).normalized();
      const float facing = -normal.dot(ray);
      if (facing < kMinFacing) continue;
      const Eigen::Vector3f point = origin + distance[n] * PixelRay(camera, origin, n);
      const float meet = normal.dot(point - origin) / -facing;  // where the ray meets the plane
      const int agree = solved && own.dot(theirs) > kAgree ? 1 : 0;
      for (int k = 0; k <= agree; ++k) {
        on_planes[k] += meet;
        ++planes[k];
      }
    }
  }
  PlaneMeet out;
  out.agreed = planes[1] > 0 || (!solved && planes[0] > 0);
  if (planes[1] > 0) {
    out.distance = on_planes[1] / static_cast<float>(planes[1]);
  } else if (planes[0] > 0) {
    out.distance = on_planes[0] / static_cast<float>(planes[0]);
  } else if (neighbours > 0) {
    out.distance = flat / static_cast<float>(neighbours);
  }
  return out;
}

// The distances along their rays of g's placed pixels, grown ring by ring from the set ones (`distance`: NaN where not
// set) by DistanceOnNeighbourPlanes. A pixel whose set neighbours' normals all disagree with its own waits (it may lie
// across a jump from them) until a ring reaches it from a side that agrees, or no ring is left: then it takes what its
// neighbours give. Returns the pixels set, in the order they were.
std::vector<size_t> GrowAlongNormals(const PhotometricCamera& camera, const Eigen::Vector3f& origin,
                                     const Image& normals, const PixelGeometry& g, std::vector<float>* distance) {
  const int w = g.width, h = g.height;
  std::vector<float>& d = *distance;
  std::vector<uint8_t> queued(d.size(), 0);
  // The placed pixels not yet set next to those of `from`, in raster order.
  auto next_ring = [&](const std::vector<size_t>& from) {
    std::vector<size_t> ring;
    for (size_t i : from) {
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const int x = static_cast<int>(i % w) + dx, y = static_cast<int>(i / w) + dy;
          if (x < 0 || y < 0 || x >= w || y >= h) continue;
          const size_t j = static_cast<size_t>(y) * w + x;
          if (!g.placed[j] || queued[j] || d[j] == d[j]) continue;
          queued[j] = 1;
          ring.push_back(j);
        }
      }
    }
    std::sort(ring.begin(), ring.end());
    return ring;
  };
  std::vector<size_t> set_now, placed, waiting;
  for (size_t i = 0; i < d.size(); ++i) {
    if (d[i] == d[i]) set_now.push_back(i);
  }
  std::vector<size_t> ring = next_ring(set_now);
  std::vector<PlaneMeet> grown;
  while (!ring.empty() || !waiting.empty()) {
    const bool last_resort = ring.empty();
    if (last_resort) {  // every pixel still waiting (each was met from a set neighbour)
      for (size_t j : waiting) {
        if (queued[j] || d[j] == d[j]) continue;
        queued[j] = 1;
        ring.push_back(j);
      }
      waiting.clear();
      std::sort(ring.begin(), ring.end());
      if (ring.empty()) break;
    }
    grown.resize(ring.size());
    for (size_t r = 0; r < ring.size(); ++r) {
      grown[r] = DistanceOnNeighbourPlanes(camera, origin, g, d, normals, static_cast<int>(ring[r] % w),
                                           static_cast<int>(ring[r] / w));
    }
    set_now.clear();
    for (size_t r = 0; r < ring.size(); ++r) {
      if (grown[r].agreed || last_resort) {
        d[ring[r]] = WithinHull(g, ring[r], grown[r].distance);
        set_now.push_back(ring[r]);
      } else {
        queued[ring[r]] = 0;  // to be met again from a pixel set later
        waiting.push_back(ring[r]);
      }
    }
    placed.insert(placed.end(), set_now.begin(), set_now.end());
    ring = next_ring(set_now);
  }
  return placed;
}

}  // namespace

absl::StatusOr<int64_t> RefillGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, const LightModel& light,
                                       const Image& normals, const PhotometricOptions& options, PixelGeometry* g) {
  if (g->placed.empty()) return 0;
  const size_t pixels = static_cast<size_t>(g->width) * g->height;
  if (normals.width != g->width || normals.height != g->height || normals.channels != 3 || g->placed.size() != pixels) {
    return absl::InvalidArgumentError(absl::StrCat("geometry refill: the normals are ", normals.width, "x",
                                                   normals.height, "x", normals.channels, ", the geometry ", g->width,
                                                   "x", g->height));
  }
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  // The mesh's pixels' distances along their rays; the placed ones are grown again from them.
  std::vector<float> distance(pixels, std::nanf(""));
  for (size_t i = 0; i < pixels; ++i) {
    if (!g->Covers(i) || g->placed[i]) continue;
    distance[i] = (Eigen::Map<const Eigen::Vector3f>(&g->points[3 * i]) - origin).dot(PixelRay(camera, origin, i));
  }
  const std::vector<size_t> replaced = GrowAlongNormals(camera, origin, normals, *g, &distance);
  // Placed pixels no ring reached (cut off from the mesh's by unplaced ones) keep their point.
  PlaceAlongRays(mesh, camera, light, options, replaced, distance, g);
  return static_cast<int64_t>(replaced.size());
}

absl::Status PhotometricOptions::Validate() const {
  auto bad = [](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("photometric options: ", what));
  };
  if (iterations < 1) return bad(absl::StrCat("iterations ", iterations, " is below 1"));
  if (table_size < 8) return bad(absl::StrCat("table_size ", table_size, " is below 8"));
  if (!(min_signal_dn >= 0) || !(min_signal_sigma >= 0) || !(min_specular_snr >= 0)) {
    return bad("min_signal_dn, min_signal_sigma and min_specular_snr must not be negative");
  }
  if (!(max_specular_sigma_deg > 0))
    return bad(absl::StrCat("max_specular_sigma_deg ", max_specular_sigma_deg, " <= 0"));
  if (!(max_albedo > 0)) return bad(absl::StrCat("max_albedo ", max_albedo, " <= 0"));
  if (specular_filter_radius < 0 || specular_filter_radius > 16) {
    return bad(absl::StrCat("specular_filter_radius ", specular_filter_radius, " is not in 0..16"));
  }
  if (!(shadow_clearance_mm >= 0))
    return bad(absl::StrCat("shadow_clearance_mm ", shadow_clearance_mm, " is negative"));
  if (geometry_fill_px < 0) return bad(absl::StrCat("geometry_fill_px ", geometry_fill_px, " is negative"));
  if (!(geometry_hull_depth_mm > 0)) {
    return bad(absl::StrCat("geometry_hull_depth_mm ", geometry_hull_depth_mm, " is not positive"));
  }
  if (geometry_refill_passes < 0 || geometry_refill_passes > 4) {
    return bad(absl::StrCat("geometry_refill_passes ", geometry_refill_passes, " is not in 0..4"));
  }
  if (threads < 0) return bad(absl::StrCat("threads ", threads, " is negative"));
  return absl::OkStatus();
}

// The per-image constants of SolvePhotometric and its per-pixel fit. A pixel's fit reads only its own images and
// geometry: the basis of PhotometricSolver::SolveAgain.
class PhotometricSolver::Pixels {
 public:
  Pixels(const LightModel& light, const std::vector<Image>& frames, const PhotometricCamera& camera,
         const PhotometricOptions& options, Twins twins)
      : light_(light),
        frames_(frames),
        camera_(camera),
        options_(options),
        t_(std::move(twins)),
        np_(static_cast<int>(t_.cross.size())),
        pm_(MakePatternMatrix(light, t_)),
        table_(light, t_.cross, options.table_size),
        origin_view_(light.ViewFromOrigin()),
        k_leak_(camera.cross_leak / std::max(1e-9, 1 - camera.cross_leak)),
        spec_gain_(static_cast<float>(1 / std::max(1e-9, 1 - camera.cross_leak))),
        g_(camera.gain_e_per_dn),
        read_dn2_(internal::ReadVarianceDn2(camera)),  // three channels summed
        lobe_limits_(options),
        min_signal_(internal::MinSignalDn(options, camera)),  // below it: not solved
        to_camera_(camera.world_to_camera.cast<float>()),
        ws_(static_cast<float>(camera.white_scale)),
        // The specular images (summed over the three channels) per unit of the model in SpecularFromView: a white
        // Lambertian surface gives white_scale * n . H, a lobe (2 pi white_scale) * sum w D G G / (4 n.v) (the 1/pi
        // of the diffuse BRDF), in each channel.
        spec_scale_(3 * 2 * kPi * ws_),
        camera_position_(camera.position_mm.cast<float>()) {}

  int width() const { return frames_[0].width; }
  int patterns() const { return np_; }
  int height() const { return frames_[0].height; }
  const PhotometricCamera& camera() const { return camera_; }
  const PhotometricOptions& options() const { return options_; }

  // One thread's working memory.
  struct Scratch {
    explicit Scratch(int np)
        : c(static_cast<size_t>(np) * 3), d(np), hp(static_cast<size_t>(np) * 3), wt(np), s(np), sw(np), model(np) {}
    std::vector<float> c, d, hp, wt, s, sw, model;
    UnitView view, open_view;
  };

  // Pixel i = (x, y) solved into `m` (its outputs zero beforehand), with its point and shadows from `geometry`.
  void Solve(int x, int y, const PixelGeometry* geometry, Scratch& s, PhotometricMaps* m) const;

 private:
  struct Diffuse {
    Eigen::Vector3f n, rho;
    float chi2 = 0;
    bool ok = false;
  };
  // The diffuse per pattern and channel (s.c, summed in s.d): the cross image less the leaked specular (parallel -
  // cross is specular); the specular images summed over the channels (s.s) with their weights (s.sw). Returns
  // kSaturated where a channel is.
  uint8_t Measure(int x, int y, Scratch& s) const;
  // Weighted least squares for u = albedo * n from `copies` images of the diffuse per pattern (s.d, per channel s.c),
  // re-solved with the lit set of each new normal; then each channel's albedo with the normal fixed, and the fit's
  // reduced chi-square. `units`: as the pixel's point sees them; null: from the origin, by the table.
  Diffuse SolveDiffuse(const UnitView* units, const Eigen::Vector3f& start, float copies, Scratch& s) const;
  // With the lobe `fit` known, the parallel images hold as much diffuse as the cross ones: s.c and s.d from both, less
  // the lobe (twice the signal).
  void SubtractLobe(int x, int y, const UnitView& units, const SpecularFit& fit, const Eigen::Vector3f& v,
                    Scratch& s) const;
  // The specular lobe of pixel (x, y) fitted (s.s, s.sw) from `units` seen along v; where it is measured, its maps
  // and noise written into `m`, else kNoSpecular added to `flags` (kSpecularBadFit where the fit is poor).
  SpecularFit FitLobe(int x, int y, const UnitView& units, const Eigen::Vector3f& diffuse_n, const Eigen::Vector3f& v,
                      Scratch& s, uint8_t* flags, PhotometricMaps* m) const;
  // Whether the units `units` leaves in sight of `point` give under half the full-on light a surface with normal n
  // would get with nothing hidden.
  bool Shadowed(const Eigen::Vector3f& point, const Eigen::Vector3f& n, const UnitView& units, Scratch& s) const;

  const LightModel& light_;
  const std::vector<Image>& frames_;
  const PhotometricCamera& camera_;
  const PhotometricOptions options_;
  const Twins t_;
  const int np_;
  const PatternMatrix pm_;
  const DiffuseTable table_;
  const UnitView origin_view_;
  const double k_leak_;
  const float spec_gain_;
  const double g_, read_dn2_;
  const internal::LobeLimits lobe_limits_;
  const double min_signal_;
  const Eigen::Matrix3f to_camera_;
  const float ws_, spec_scale_;
  const Eigen::Vector3f camera_position_;
};

uint8_t PhotometricSolver::Pixels::Measure(int x, int y, Scratch& s) const {
  uint8_t flags = 0;
  for (int p = 0; p < np_; ++p) {
    const float* cr = frames_[static_cast<size_t>(t_.cross[p])].at(x, y);
    const float* pa = frames_[static_cast<size_t>(t_.parallel[p])].at(x, y);
    float sum = 0, spec = 0, level = 0;
    for (int ch = 0; ch < 3; ++ch) {
      if (cr[ch] >= camera_.saturation_dn || pa[ch] >= camera_.saturation_dn) flags |= kSaturated;
      const float v = cr[ch] - static_cast<float>(k_leak_) * (pa[ch] - cr[ch]);
      s.c[static_cast<size_t>(p) * 3 + ch] = v;
      sum += v;
      spec += pa[ch] - cr[ch];
      level += std::max(0.f, pa[ch]) + std::max(0.f, cr[ch]);
    }
    s.d[p] = sum;
    s.s[p] = spec * spec_gain_;
    s.sw[p] = 1.f / (spec_gain_ * spec_gain_ * static_cast<float>(level / g_ + 2 * read_dn2_));
  }
  return flags;
}

PhotometricSolver::Pixels::Diffuse PhotometricSolver::Pixels::SolveDiffuse(const UnitView* units,
                                                                           const Eigen::Vector3f& start, float copies,
                                                                           Scratch& s) const {
  auto lookup = [&](const Eigen::Vector3f& n) {
    if (units != nullptr) {
      DiffuseFromView(*units, pm_, n, s.hp.data());
    } else {
      table_.Lookup(n, s.hp.data());
    }
  };
  auto h_scaled = [&](int p) {
    return Eigen::Vector3f(Eigen::Map<const Eigen::Vector3f>(&s.hp[static_cast<size_t>(p) * 3]) * ws_ * copies);
  };
  Diffuse r;
  Eigen::Vector3f n = start, u = start;
  const float read = copies * static_cast<float>(read_dn2_);
  for (int it = 0; it < std::max(1, options_.iterations); ++it) {
    lookup(n);
    Eigen::Matrix3f a = Eigen::Matrix3f::Zero();
    Eigen::Vector3f b = Eigen::Vector3f::Zero();
    for (int p = 0; p < np_; ++p) {
      const Eigen::Vector3f hs = h_scaled(p);
      // The variance at the level the model predicts (the measured level on the first pass).
      const float level = r.ok ? std::max(0.f, u.dot(hs)) : std::max(0.f, s.d[p]);
      s.wt[p] = 1.f / (level / static_cast<float>(g_) + read);
      a += s.wt[p] * hs * hs.transpose();
      b += s.wt[p] * s.d[p] * hs;
    }
    const Eigen::Vector3f next = a.ldlt().solve(b);
    if (!next.allFinite() || next.norm() < 1e-9f) break;
    u = next;
    n = u.normalized();
    r.ok = true;
  }
  if (!r.ok) return r;
  lookup(n);
  float s2 = 0;
  Eigen::Vector3f num = Eigen::Vector3f::Zero();
  for (int p = 0; p < np_; ++p) {
    const Eigen::Vector3f hs = h_scaled(p);
    const float sp = n.dot(hs);
    const float level = std::max(0.f, u.dot(hs));
    s.wt[p] = 1.f / (level / static_cast<float>(g_) + read);
    s2 += s.wt[p] * sp * sp;
    for (int ch = 0; ch < 3; ++ch) num[ch] += s.wt[p] * s.c[static_cast<size_t>(p) * 3 + ch] * sp;
    const float e = s.d[p] - level;
    r.chi2 += s.wt[p] * e * e;
  }
  r.chi2 /= static_cast<float>(std::max(1, np_ - 3));
  r.n = n;
  r.rho = num / std::max(1e-12f, s2);
  return r;
}

void PhotometricSolver::Pixels::SubtractLobe(int x, int y, const UnitView& units, const SpecularFit& fit,
                                             const Eigen::Vector3f& v, Scratch& s) const {
  SpecularFromView(units, pm_, fit.n, v, fit.alpha, s.model.data());
  for (int p = 0; p < np_; ++p) {
    const float* cr = frames_[static_cast<size_t>(t_.cross[p])].at(x, y);
    const float* pa = frames_[static_cast<size_t>(t_.parallel[p])].at(x, y);
    const float lobe = fit.rho * s.model[static_cast<size_t>(p)] * spec_scale_ / 3;  // per channel
    float sum = 0;
    for (int ch = 0; ch < 3; ++ch) {
      const float v2 = cr[ch] + pa[ch] - (1 + static_cast<float>(camera_.cross_leak)) * lobe;
      s.c[static_cast<size_t>(p) * 3 + ch] = v2;
      sum += v2;
    }
    s.d[p] = sum;
  }
}

SpecularFit PhotometricSolver::Pixels::FitLobe(int x, int y, const UnitView& units, const Eigen::Vector3f& diffuse_n,
                                               const Eigen::Vector3f& v, Scratch& s, uint8_t* flags,
                                               PhotometricMaps* m) const {
  const size_t i = static_cast<size_t>(y) * width() + x;
  const float spec_snr = s.s[t_.full] * std::sqrt(s.sw[t_.full]);
  // From the diffuse normal and from the lobe's centroid; fitted wherever it can be, faint or not: the diffuse solved
  // again after it uses it.
  std::vector<Eigen::Vector3f> starts = {diffuse_n};
  const Eigen::Map<const Eigen::VectorXf> sv(s.s.data(), np_);
  const Eigen::Vector4f mom = pm_.moments.topRows<4>() * sv;
  if (mom[0] > 0 && mom.tail<3>().norm() > 1e-6f) {
    const Eigen::Vector3f r = mom.tail<3>().normalized();
    if ((r + v).norm() > 1e-3f) starts.push_back((r + v).normalized());
  }
  const SpecularFit fit = FitSpecular(units, pm_, s.s.data(), s.sw.data(), v, starts, spec_scale_);
  const bool measured = fit.ok && internal::LobeMeasured(lobe_limits_, spec_snr, fit.var_n, fit.rho, fit.var_rho,
                                                         fit.var_log_alpha, fit.alpha);
  if (!measured) {
    *flags |= kNoSpecular;
    return fit;
  }
  if (fit.chi2 > 4) *flags |= kSpecularBadFit;
  std::copy(fit.n.data(), fit.n.data() + 3, m->specular_normal_raw.at(x, y));
  m->specular.at(x, y)[0] = fit.rho;
  m->roughness.at(x, y)[0] = fit.alpha;
  internal::Work(m, internal::kVarNormal)[i] = fit.var_n;
  m->specular_sigma.at(x, y)[0] = std::sqrt(fit.var_n) * 180 / kPi;
  internal::Work(m, internal::kVarLogAlpha)[i] = fit.var_log_alpha;
  return fit;
}

bool PhotometricSolver::Pixels::Shadowed(const Eigen::Vector3f& point, const Eigen::Vector3f& n, const UnitView& units,
                                         Scratch& s) const {
  light_.ViewFrom(point.cast<double>(), nullptr, &s.open_view);
  float all = 0, seen = 0;
  for (size_t l = 0; l < s.open_view.gain.size(); ++l) {
    const float cosine = std::max(0.f, n.dot(s.open_view.direction[l]));
    all += s.open_view.gain[l] * cosine;
    seen += units.gain[l] * cosine;
  }
  return seen < 0.5f * all;
}

void PhotometricSolver::Pixels::Solve(int x, int y, const PixelGeometry* geometry, Scratch& s,
                                      PhotometricMaps* maps) const {
  PhotometricMaps& m = *maps;
  const size_t i = static_cast<size_t>(y) * width() + x;
  uint8_t flags = Measure(x, y, s);
  if (s.d[t_.full] < min_signal_) {
    m.flags[i] = flags | kLowSignal;
    return;
  }
  // The units as this pixel's surface point sees them (with geometry), else from the stage origin.
  const bool exact = geometry != nullptr && geometry->Covers(i);
  Eigen::Vector3f point = Eigen::Vector3f::Zero();
  if (exact) {
    point = Eigen::Map<const Eigen::Vector3f>(&geometry->points[3 * i]);
    light_.ViewFrom(point.cast<double>(), geometry->Visible(i), &s.view);
  }
  const UnitView& units = exact ? s.view : origin_view_;
  // First guess: the gradients' differences (exact on a full sphere of light); else facing the camera.
  Eigen::Vector3f n0 = (camera_position_ - point).normalized();
  if (t_.xp >= 0 && t_.xm >= 0 && t_.yp >= 0 && t_.ym >= 0 && t_.zp >= 0 && t_.zm >= 0) {
    const Eigen::Vector3f guess(s.d[t_.xp] - s.d[t_.xm], s.d[t_.yp] - s.d[t_.ym], s.d[t_.zp] - s.d[t_.zm]);
    if (guess.norm() > 1e-6f) n0 = guess.normalized();
  }
  Diffuse diffuse = SolveDiffuse(exact ? &units : nullptr, n0, 1, s);
  if (!diffuse.ok) {
    m.flags[i] = flags | kLowSignal;
    return;
  }

  // Specular: the lobe fitted to parallel - cross, seen along the pixel's ray.
  const Eigen::Vector3f v = camera_.rays.empty() ? Eigen::Vector3f((camera_position_ - point).normalized())
                                                 : Eigen::Vector3f(-camera_.rays[i]);
  const SpecularFit fit = FitLobe(x, y, units, diffuse.n, v, s, &flags, &m);
  const float full_on = s.d[t_.full];  // the cross full-on, for the confidence
  // Solved again from both polarizations, less the fitted lobe: the lobe fitted to 19 images stands for the specular in
  // each with a fraction of the noise of parallel - cross itself, measured or not (a faint lobe is fitted as faint,
  // one that reflects off the dome as none).
  if (fit.converged && fit.chi2 <= 4) {
    SubtractLobe(x, y, units, fit, v, s);
    const Diffuse both = SolveDiffuse(exact ? &units : nullptr, diffuse.n, 2, s);
    if (both.ok) diffuse = both;
  }
  const Eigen::Vector3f n = diffuse.n;
  if (diffuse.chi2 > 4) flags |= kBadFit;
  if (exact && Shadowed(point, n, units, s)) flags |= kShadowed;
  const Eigen::Vector3f nc = to_camera_ * n;
  std::copy(n.data(), n.data() + 3, m.diffuse_normal_world.at(x, y));
  std::copy(nc.data(), nc.data() + 3, m.diffuse_normal_camera.at(x, y));
  if (camera_.mosaic.has_value()) {
    internal::Work(&m, internal::kOwnAlbedo)[i] = diffuse.rho[camera_.mosaic->Color(x, y)];
  } else {
    std::copy(diffuse.rho.data(), diffuse.rho.data() + 3, m.albedo.at(x, y));
  }
  m.fit_residual.at(x, y)[0] = diffuse.chi2;
  m.confidence.at(x, y)[0] =
      internal::Confidence(full_on, static_cast<float>(g_), static_cast<float>(read_dn2_), diffuse.chi2, flags);
  m.flags[i] = flags;
}

namespace {

// The maps a pixel's fit writes (the regularized specular normals are the passes' own), zero where nothing is solved.
std::array<Image*, 9> FitImages(PhotometricMaps* m) {
  return {&m->diffuse_normal_world,
          &m->diffuse_normal_camera,
          &m->albedo,
          &m->specular_normal_raw,
          &m->specular,
          &m->roughness,
          &m->specular_sigma,
          &m->confidence,
          &m->fit_residual};
}

// Pixel i's outputs in `m` (and its working memory) zero, as a solve starts from.
void ClearPixel(size_t i, PhotometricMaps* m) {
  for (Image* image : FitImages(m)) {
    const size_t c = static_cast<size_t>(image->channels);
    std::fill_n(&image->pixels[c * i], c, 0.f);
  }
  m->flags[i] = 0;
  for (internal::WorkSlot slot : {internal::kVarNormal, internal::kVarLogAlpha, internal::kOwnAlbedo}) {
    internal::Work(m, slot)[i] = 0;
  }
}

}  // namespace

absl::StatusOr<std::unique_ptr<PhotometricSolver>> PhotometricSolver::Create(const LightModel& light,
                                                                             const std::vector<Image>& frames,
                                                                             const PhotometricCamera& camera,
                                                                             const PhotometricOptions& options) {
  if (frames.size() != light.patterns.size() || frames.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("photometric stereo: ", frames.size(), " images for ", light.patterns.size(), " patterns"));
  }
  const int w = frames[0].width, h = frames[0].height;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (frames[i].width != w || frames[i].height != h || frames[i].channels != 3) {
      return absl::InvalidArgumentError(
          absl::StrCat("photometric stereo: the image of pattern \"", light.patterns[i].name, "\" is ", frames[i].width,
                       "x", frames[i].height, "x", frames[i].channels, ", not ", w, "x", h, "x3"));
    }
  }
  if (!camera.rays.empty() && camera.rays.size() != static_cast<size_t>(w) * h) {
    return absl::InvalidArgumentError(
        absl::StrCat("photometric stereo: ", camera.rays.size(), " camera rays for ", w, "x", h, " pixels"));
  }
  auto twins = PairPatterns(light);
  if (!twins.ok()) return twins.status();
  return std::unique_ptr<PhotometricSolver>(
      new PhotometricSolver(std::make_unique<Pixels>(light, frames, camera, options, std::move(*twins))));
}

PhotometricSolver::PhotometricSolver(std::unique_ptr<Pixels> pixels) : pixels_(std::move(pixels)) {}
PhotometricSolver::~PhotometricSolver() = default;

absl::Status PhotometricSolver::CheckGeometry(const PixelGeometry* geometry) const {
  if (geometry != nullptr && (geometry->width != pixels_->width() || geometry->height != pixels_->height())) {
    return absl::InvalidArgumentError(absl::StrCat("photometric stereo: the geometry is ", geometry->width, "x",
                                                   geometry->height, ", the images ", pixels_->width(), "x",
                                                   pixels_->height()));
  }
  return absl::OkStatus();
}

void PhotometricSolver::SolvePixels(const PixelGeometry* geometry, const std::vector<uint8_t>* only) {
  const int w = pixels_->width();
  ParallelRows(pixels_->height(), pixels_->options().threads, [&](int y0, int y1) {
    Pixels::Scratch scratch(pixels_->patterns());
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        if (only != nullptr && (*only)[i] == 0) continue;
        if (only != nullptr) ClearPixel(i, &fits_);
        pixels_->Solve(x, y, geometry, scratch, &fits_);
      }
    }
  });
}

PhotometricMaps PhotometricSolver::Finish(PhotometricMaps m) const {
  const PhotometricCamera& camera = pixels_->camera();
  const PhotometricOptions& options = pixels_->options();
  if (camera.mosaic.has_value()) {
    internal::DemosaicAlbedo(*camera.mosaic, internal::Work(&m, internal::kOwnAlbedo),
                             static_cast<float>(options.max_albedo), options.threads, &m);
  } else {
    internal::FlagImplausibleRgbAlbedo(static_cast<float>(options.max_albedo), &m);
  }
  internal::RegularizeSpecular(options.specular_filter_radius, options.threads, camera.world_to_camera.cast<float>(),
                               &m);
  return m;
}

absl::StatusOr<PhotometricMaps> PhotometricSolver::Solve(const PixelGeometry* geometry, bool again) {
  if (absl::Status s = CheckGeometry(geometry); !s.ok()) return s;
  internal::PrepareMaps(pixels_->width(), pixels_->height(), &fits_);
  // The maps are zero where nothing is solved.
  for (Image* image : FitImages(&fits_)) std::fill(image->pixels.begin(), image->pixels.end(), 0.f);
  std::fill(fits_.flags.begin(), fits_.flags.end(), 0);
  internal::Work(&fits_, internal::kVarNormal);  // sized here, before the threads write it
  std::fill(fits_.work.begin(), fits_.work.end(), 0.f);
  SolvePixels(geometry, nullptr);
  solved_ = again;
  return Finish(again ? fits_ : std::move(fits_));
}

absl::StatusOr<PhotometricMaps> PhotometricSolver::SolveAgain(const PixelGeometry& geometry,
                                                              const std::vector<uint8_t>& redo) {
  if (!solved_) {
    return absl::FailedPreconditionError(
        "photometric stereo: solved again before it was solved once to be solved again");
  }
  if (absl::Status s = CheckGeometry(&geometry); !s.ok()) return s;
  if (redo.size() != fits_.flags.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("photometric stereo: ", redo.size(), " pixels to solve again of ", fits_.flags.size()));
  }
  SolvePixels(&geometry, &redo);
  return Finish(fits_);
}

absl::StatusOr<PhotometricMaps> SolvePhotometric(const LightModel& light, const std::vector<Image>& frames,
                                                 const PhotometricCamera& camera, const PhotometricOptions& options,
                                                 const PixelGeometry* geometry) {
  auto solver = PhotometricSolver::Create(light, frames, camera, options);
  if (!solver.ok()) return solver.status();
  return (*solver)->Solve(geometry, /*again=*/false);
}

}  // namespace stage::processing
