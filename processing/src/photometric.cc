// Photometric stereo under spherical gradient illumination: see photometric.h.
#include "stage/processing/photometric.h"

#include "photometric_internal.h"

#include <Eigen/Dense>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "stage/common/ggx.h"

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

void SpecularFromView(const UnitView& view, const PatternMatrix& pm, const Eigen::Vector3f& n,
                      const Eigen::Vector3f& v, float alpha, float* m) {
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
  for (auto [image, channels] : std::initializer_list<std::pair<Image*, int>>{
           {&m->diffuse_normal_world, 3}, {&m->diffuse_normal_camera, 3}, {&m->albedo, 3},
           {&m->specular_normal_world, 3}, {&m->specular_normal_camera, 3}, {&m->specular_normal_raw, 3},
           {&m->specular, 1}, {&m->roughness, 1}, {&m->specular_sigma, 1}, {&m->confidence, 1},
           {&m->fit_residual, 1}}) {
    image->width = width;
    image->height = height;
    image->channels = channels;
    image->pixels.resize(static_cast<size_t>(width) * height * channels);
  }
  m->flags.resize(static_cast<size_t>(width) * height);
}

// A local Wiener (Lee) filter of the departure of the specular normal from the diffuse one (3 components) and of log
// roughness, each with its own per-pixel noise: in a (2r+1)^2 window of the pixels with a lobe on the same side of an
// edge, the inverse-variance weighted mean mu and the spread s^2 about it; the pixel keeps mu + k (x - mu) with
// k = signal / (signal + noise), signal = max(0, s^2 - mean noise).
void RegularizeSpecular(int radius, int threads, const Eigen::Matrix3f& to_camera, PhotometricMaps* maps) {
  PhotometricMaps& m = *maps;
  const int w = m.width, h = m.height;
  const float* var_n = Work(&m, kVarNormal);
  const float* var_la = Work(&m, kVarLogAlpha);
  float* delta = Work(&m, kDelta);
  float* log_alpha = Work(&m, kLogAlpha);
  const float* nd = m.diffuse_normal_world.pixels.data();
  auto has_lobe = [&](size_t i) { return (m.flags[i] & (kLowSignal | kNoSpecular)) == 0; };
  ParallelRows(h, threads, [&](int y0, int y1) {
    for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) {
      if (!has_lobe(i)) continue;
      for (int k = 0; k < 3; ++k) delta[3 * i + k] = m.specular_normal_raw.pixels[3 * i + k] - nd[3 * i + k];
      log_alpha[i] = std::log(m.roughness.pixels[i]);
    }
  });
  ParallelRows(h, threads, [&](int y0, int y1) {
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        if (x % kStreamRun == 0) {  // a run without a lobe: zeros straight to memory
          const int n = std::min(kStreamRun, w - x);
          bool any = false;
          for (int k = 0; k < n; ++k) any |= has_lobe(i + k);
          if (!any) {
            StreamZeros(&m.specular_normal_world.pixels[3 * i], 3 * static_cast<size_t>(n));
            StreamZeros(&m.specular_normal_camera.pixels[3 * i], 3 * static_cast<size_t>(n));
            x += n - 1;
            continue;
          }
        }
        float* sw = &m.specular_normal_world.pixels[3 * i];
        float* sc = &m.specular_normal_camera.pixels[3 * i];
        if (!has_lobe(i)) {
          std::fill(sw, sw + 3, 0.f);
          std::fill(sc, sc + 3, 0.f);
          continue;
        }
        const float* n0 = &nd[3 * i];
        // Sums over the window: weights, weighted values, values and squares, noise; normal (3) then log alpha.
        float wn = 0, wl = 0, mn[3] = {0, 0, 0}, ml = 0, sn[3] = {0, 0, 0}, sl = 0, qn = 0, ql = 0, nn = 0, nl = 0;
        int count = 0;
        if (radius > 0) {
          for (int yy = std::max(0, y - radius); yy <= std::min(h - 1, y + radius); ++yy) {
            for (int xx = std::max(0, x - radius); xx <= std::min(w - 1, x + radius); ++xx) {
              const size_t j = static_cast<size_t>(yy) * w + xx;
              if (!has_lobe(j)) continue;
              const float* n1 = &nd[3 * j];
              if (n0[0] * n1[0] + n0[1] * n1[1] + n0[2] * n1[2] <= 0.866f) continue;
              const float a = 1 / std::max(1e-12f, var_n[j]), b = 1 / std::max(1e-12f, var_la[j]);
              for (int c = 0; c < 3; ++c) {
                const float v = delta[3 * j + c];
                mn[c] += a * v;
                sn[c] += v;
                qn += v * v;
              }
              wn += a;
              nn += var_n[j];
              ml += b * log_alpha[j];
              sl += log_alpha[j];
              ql += log_alpha[j] * log_alpha[j];
              wl += b;
              nl += var_la[j];
              ++count;
            }
          }
        }
        float dn[3] = {delta[3 * i], delta[3 * i + 1], delta[3 * i + 2]};
        float la = log_alpha[i];
        if (count >= 3) {
          const float inv = 1.f / static_cast<float>(count);
          float spread = qn * inv;
          for (int c = 0; c < 3; ++c) {
            mn[c] /= wn;
            spread += mn[c] * mn[c] - 2 * mn[c] * sn[c] * inv;
          }
          const float signal = std::max(0.f, spread - nn * inv);
          const float k = signal / (signal + std::max(1e-12f, var_n[i]));
          for (int c = 0; c < 3; ++c) dn[c] = mn[c] + k * (dn[c] - mn[c]);
          ml /= wl;
          const float spread_l = ql * inv + ml * ml - 2 * ml * sl * inv;
          const float signal_l = std::max(0.f, spread_l - nl * inv);
          const float kl = signal_l / (signal_l + std::max(1e-12f, var_la[i]));
          la = ml + kl * (la - ml);
        }
        const Eigen::Vector3f ns = Eigen::Vector3f(n0[0] + dn[0], n0[1] + dn[1], n0[2] + dn[2]).normalized();
        const Eigen::Vector3f nc = to_camera * ns;
        std::copy(ns.data(), ns.data() + 3, sw);
        std::copy(nc.data(), nc.data() + 3, sc);
        m.roughness.pixels[i] = std::exp(la);
      }
    }
    _mm_sfence();
  });
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
  float var_n = 0;      // variance of the normal's direction, rad^2 (both tangent axes)
  float var_log_alpha = 0;  // of log(alpha)
  float var_rho = 0;    // of rho
  float chi2 = 0;       // reduced
  bool converged = false;  // a fit was made (rho may be 0: no lobe)
  bool ok = false;         // and found a lobe
};

constexpr float kMinAlpha = internal::kMinLobeAlpha, kMaxAlpha = 1.5f;

// A frame of the plane tangent to unit n: the normal is moved as n + a t1 + b t2, normalized.
void TangentFrame(const Eigen::Vector3f& n, Eigen::Vector3f* t1, Eigen::Vector3f* t2) {
  *t1 = (std::abs(n.x()) < 0.9f ? Eigen::Vector3f::UnitX() : Eigen::Vector3f::UnitY()).cross(n).normalized();
  *t2 = n.cross(*t1);
}

// The finite-difference steps of the lobe's parameters: tangent offsets of the normal, log alpha.
constexpr float kStep[3] = {2e-3f, 2e-3f, 1e-2f};

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
    *a_out = alpha * std::exp(d[2]);
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
    const Eigen::Matrix4f info = j4.transpose() * j4 + 1e-12f * Eigen::Matrix4f::Identity();
    const Eigen::Matrix4f cov = info.inverse();
    fit.var_n = std::max(0.f, cov(0, 0) + cov(1, 1));
    fit.var_log_alpha = std::max(0.f, cov(2, 2));
    fit.var_rho = std::max(0.f, cov(3, 3));
    if (!cov.allFinite()) fit.var_n = fit.var_log_alpha = fit.var_rho = 1e30f;
  }
  fit.converged = fit.n.allFinite() && std::isfinite(fit.chi2);
  fit.ok = fit.converged && rho > 0;
  return fit;
}

}  // namespace

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) * 180.0 / M_PI;
}

PixelGeometry TraceGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, int width, int height,
                            const LightModel& light, int threads) {
  PixelGeometry g;
  g.width = width;
  g.height = height;
  g.words = (light.units() + 63) / 64;
  const size_t pixels = static_cast<size_t>(width) * height;
  g.points.assign(3 * pixels, std::nanf(""));
  g.visible.assign(pixels * static_cast<size_t>(g.words), 0);
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  std::vector<Eigen::Vector3f> units;
  for (const Eigen::Vector3d& d : light.directions) units.push_back((d * light.radius_mm).cast<float>());
  ParallelRows(height, threads, [&](int y0, int y1) {
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < width; ++x) {
        const size_t i = static_cast<size_t>(y) * width + x;
        const Eigen::Vector3f dir =
            camera.rays.empty() ? Eigen::Vector3f(-origin.normalized()) : camera.rays[i];
        MeshHit hit;
        if (!mesh.Nearest(origin, dir, INFINITY, &hit)) continue;
        const auto& t = mesh.mesh().triangles[static_cast<size_t>(hit.triangle)];
        const Eigen::Vector3f& p0 = mesh.mesh().positions[static_cast<size_t>(t[0])];
        Eigen::Vector3f face = (mesh.mesh().positions[static_cast<size_t>(t[1])] - p0)
                                   .cross(mesh.mesh().positions[static_cast<size_t>(t[2])] - p0)
                                   .normalized();
        if (face.dot(dir) > 0) face = -face;
        const Eigen::Vector3f point = origin + hit.t * dir;
        std::copy(point.data(), point.data() + 3, &g.points[3 * i]);
        // As the light meets the surface: from just off it, towards every unit in front of its face.
        const Eigen::Vector3f start = point + 1e-3f * face;
        uint64_t* bits = &g.visible[i * static_cast<size_t>(g.words)];
        for (size_t l = 0; l < units.size(); ++l) {
          if (face.dot(units[l] - point) <= 0) continue;
          if (mesh.Occluded(start, units[l])) continue;
          bits[l / 64] |= uint64_t{1} << (l % 64);
        }
      }
    }
  });
  return g;
}

absl::StatusOr<PhotometricMaps> SolvePhotometric(const LightModel& light, const std::vector<Image>& frames,
                                                 const PhotometricCamera& camera, const PhotometricOptions& options,
                                                 const PixelGeometry* geometry) {
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
  if (geometry != nullptr && (geometry->width != w || geometry->height != h)) {
    return absl::InvalidArgumentError(absl::StrCat("photometric stereo: the geometry is ", geometry->width, "x",
                                                   geometry->height, ", the images ", w, "x", h));
  }
  if (!camera.rays.empty() && camera.rays.size() != static_cast<size_t>(w) * h) {
    return absl::InvalidArgumentError(
        absl::StrCat("photometric stereo: ", camera.rays.size(), " camera rays for ", w, "x", h, " pixels"));
  }
  auto twins = PairPatterns(light);
  if (!twins.ok()) return twins.status();
  const Twins& t = *twins;
  const int np = static_cast<int>(t.cross.size());
  const PatternMatrix pm = MakePatternMatrix(light, t);
  const DiffuseTable table(light, t.cross, options.table_size);
  const UnitView origin_view = light.ViewFromOrigin();

  PhotometricMaps m;
  internal::PrepareMaps(w, h, &m);
  // The maps are zero where nothing is solved.
  for (Image* image : {&m.diffuse_normal_world, &m.diffuse_normal_camera, &m.albedo, &m.specular_normal_raw,
                       &m.specular, &m.roughness, &m.specular_sigma, &m.confidence, &m.fit_residual}) {
    std::fill(image->pixels.begin(), image->pixels.end(), 0.f);
  }
  std::fill(m.flags.begin(), m.flags.end(), 0);
  // Per-pixel noise of the specular fit, for the regularization.
  float* var_n = internal::Work(&m, internal::kVarNormal);
  float* var_log_alpha = internal::Work(&m, internal::kVarLogAlpha);

  const double k_leak = camera.cross_leak / std::max(1e-9, 1 - camera.cross_leak);
  const float spec_gain = static_cast<float>(1 / std::max(1e-9, 1 - camera.cross_leak));
  const double g = camera.gain_e_per_dn;
  const double read_dn2 = internal::ReadVarianceDn2(camera);  // three channels summed
  const double min_signal = internal::MinSignalDn(options, camera);  // below it: not solved
  const Eigen::Matrix3f to_camera = camera.world_to_camera.cast<float>();
  const float ws = static_cast<float>(camera.white_scale);
  // The specular images (summed over the three channels) per unit of the model in SpecularFromView: a white
  // Lambertian surface gives white_scale * n . H, a lobe (2 pi white_scale) * sum w D G G / (4 n.v) (the 1/pi of the
  // diffuse BRDF), in each channel.
  const float spec_scale = 3 * 2 * kPi * ws;
  const Eigen::Vector3f camera_position = camera.position_mm.cast<float>();

  ParallelRows(h, options.threads, [&](int y0, int y1) {
    std::vector<float> c(static_cast<size_t>(np) * 3), d(np), hp(static_cast<size_t>(np) * 3), wt(np), s(np),
        sw(np), model(np);
    UnitView view, open_view;
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        uint8_t flags = 0;
        // Diffuse per pattern and channel: the cross image less the leaked specular (parallel - cross is specular);
        // and the specular images, summed over the channels, with their noise.
        for (int p = 0; p < np; ++p) {
          const float* cr = frames[static_cast<size_t>(t.cross[p])].at(x, y);
          const float* pa = frames[static_cast<size_t>(t.parallel[p])].at(x, y);
          float sum = 0, spec = 0, level = 0;
          for (int ch = 0; ch < 3; ++ch) {
            if (cr[ch] >= camera.saturation_dn || pa[ch] >= camera.saturation_dn) flags |= kSaturated;
            const float v = cr[ch] - static_cast<float>(k_leak) * (pa[ch] - cr[ch]);
            c[static_cast<size_t>(p) * 3 + ch] = v;
            sum += v;
            spec += pa[ch] - cr[ch];
            level += std::max(0.f, pa[ch]) + std::max(0.f, cr[ch]);
          }
          d[p] = sum;
          s[p] = spec * spec_gain;
          sw[p] = 1.f / (spec_gain * spec_gain * static_cast<float>(level / g + 2 * read_dn2));
        }
        if (d[t.full] < min_signal) {
          m.flags[i] = flags | kLowSignal;
          continue;
        }
        // The units as this pixel's surface point sees them (with geometry), else from the stage origin.
        const bool exact = geometry != nullptr && geometry->Covers(i);
        Eigen::Vector3f point = Eigen::Vector3f::Zero();
        if (exact) {
          point = Eigen::Map<const Eigen::Vector3f>(&geometry->points[3 * i]);
          light.ViewFrom(point.cast<double>(), geometry->Visible(i), &view);
        }
        const UnitView& units = exact ? view : origin_view;
        auto lookup = [&](const Eigen::Vector3f& n) {
          if (exact) {
            DiffuseFromView(units, pm, n, hp.data());
          } else {
            table.Lookup(n, hp.data());
          }
        };
        // First guess: the gradients' differences (exact on a full sphere of light); else facing the camera.
        Eigen::Vector3f n0 = (camera_position - point).normalized();
        if (t.xp >= 0 && t.xm >= 0 && t.yp >= 0 && t.ym >= 0 && t.zp >= 0 && t.zm >= 0) {
          const Eigen::Vector3f guess(d[t.xp] - d[t.xm], d[t.yp] - d[t.ym], d[t.zp] - d[t.zm]);
          if (guess.norm() > 1e-6f) n0 = guess.normalized();
        }
        // Weighted least squares for u = albedo * n from `copies` images of the diffuse per pattern (summed in d,
        // per channel in c), re-solved with the lit set of each new normal; then each channel's albedo with the
        // normal fixed, and the fit's reduced chi-square.
        struct Diffuse {
          Eigen::Vector3f n, rho;
          float chi2 = 0;
          bool ok = false;
        };
        auto solve_diffuse = [&](const Eigen::Vector3f& start, float copies) {
          Diffuse r;
          Eigen::Vector3f n = start, u = start;
          const float read = copies * static_cast<float>(read_dn2);
          for (int it = 0; it < std::max(1, options.iterations); ++it) {
            lookup(n);
            Eigen::Matrix3f a = Eigen::Matrix3f::Zero();
            Eigen::Vector3f b = Eigen::Vector3f::Zero();
            for (int p = 0; p < np; ++p) {
              const Eigen::Vector3f hs = Eigen::Map<const Eigen::Vector3f>(&hp[static_cast<size_t>(p) * 3]) * ws * copies;
              // The variance at the level the model predicts (the measured level on the first pass).
              const float level = r.ok ? std::max(0.f, u.dot(hs)) : std::max(0.f, d[p]);
              wt[p] = 1.f / (level / static_cast<float>(g) + read);
              a += wt[p] * hs * hs.transpose();
              b += wt[p] * d[p] * hs;
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
          for (int p = 0; p < np; ++p) {
            const Eigen::Vector3f hs = Eigen::Map<const Eigen::Vector3f>(&hp[static_cast<size_t>(p) * 3]) * ws * copies;
            const float sp = n.dot(hs);
            const float level = std::max(0.f, u.dot(hs));
            wt[p] = 1.f / (level / static_cast<float>(g) + read);
            s2 += wt[p] * sp * sp;
            for (int ch = 0; ch < 3; ++ch) num[ch] += wt[p] * c[static_cast<size_t>(p) * 3 + ch] * sp;
            const float e = d[p] - level;
            r.chi2 += wt[p] * e * e;
          }
          r.chi2 /= static_cast<float>(std::max(1, np - 3));
          r.n = n;
          r.rho = num / std::max(1e-12f, s2);
          return r;
        };
        Diffuse diffuse = solve_diffuse(n0, 1);
        if (!diffuse.ok) {
          m.flags[i] = flags | kLowSignal;
          continue;
        }

        // Specular: the lobe fitted to parallel - cross, from the diffuse normal and from the lobe's centroid.
        const Eigen::Vector3f v = camera.rays.empty() ? Eigen::Vector3f((camera_position - point).normalized())
                                                      : Eigen::Vector3f(-camera.rays[i]);
        const float spec_snr = s[t.full] * std::sqrt(sw[t.full]);
        // Fitted wherever it can be, faint or not: the diffuse below uses it.
        std::vector<Eigen::Vector3f> starts = {diffuse.n};
        const Eigen::Map<const Eigen::VectorXf> sv(s.data(), np);
        const Eigen::Vector4f mom = pm.moments.topRows<4>() * sv;
        if (mom[0] > 0 && mom.tail<3>().norm() > 1e-6f) {
          const Eigen::Vector3f r = mom.tail<3>().normalized();
          if ((r + v).norm() > 1e-3f) starts.push_back((r + v).normalized());
        }
        const SpecularFit fit = FitSpecular(units, pm, s.data(), sw.data(), v, starts, spec_scale);
        const bool measured = fit.ok && internal::LobeMeasured(options, spec_snr, fit.var_n, fit.rho, fit.var_rho,
                                                               fit.var_log_alpha, fit.alpha);
        if (!measured) {
          flags |= kNoSpecular;
        } else {
          if (fit.chi2 > 4) flags |= kSpecularBadFit;
          std::copy(fit.n.data(), fit.n.data() + 3, m.specular_normal_raw.at(x, y));
          m.specular.at(x, y)[0] = fit.rho;
          m.roughness.at(x, y)[0] = fit.alpha;
          var_n[i] = fit.var_n;
          m.specular_sigma.at(x, y)[0] = std::sqrt(fit.var_n) * 180 / kPi;
          var_log_alpha[i] = fit.var_log_alpha;
        }
        const float full_on = d[t.full];  // the cross full-on, for the confidence
        // With the specular known, the parallel images hold as much diffuse as the cross ones: solve again from
        // both, less the fitted lobe (twice the signal). The lobe fitted to 19 images stands for the specular in
        // each with a fraction of the noise of parallel - cross itself, measured or not (a faint lobe is fitted as
        // faint, one that reflects off the dome as none).
        if (fit.converged && fit.chi2 <= 4) {
          SpecularFromView(units, pm, fit.n, v, fit.alpha, model.data());
          for (int p = 0; p < np; ++p) {
            const float* cr = frames[static_cast<size_t>(t.cross[p])].at(x, y);
            const float* pa = frames[static_cast<size_t>(t.parallel[p])].at(x, y);
            const float lobe = fit.rho * model[static_cast<size_t>(p)] * spec_scale / 3;  // per channel
            float sum = 0;
            for (int ch = 0; ch < 3; ++ch) {
              const float v2 = cr[ch] + pa[ch] - (1 + static_cast<float>(camera.cross_leak)) * lobe;
              c[static_cast<size_t>(p) * 3 + ch] = v2;
              sum += v2;
            }
            d[p] = sum;
          }
          const Diffuse both = solve_diffuse(diffuse.n, 2);
          if (both.ok) diffuse = both;
        }
        const Eigen::Vector3f n = diffuse.n;
        if (diffuse.chi2 > 4) flags |= kBadFit;
        if (exact) {
          // Shadow: the share of the full-on light nothing hides from the point.
          light.ViewFrom(point.cast<double>(), nullptr, &open_view);
          float all = 0, seen = 0;
          for (size_t l = 0; l < open_view.gain.size(); ++l) {
            const float cosine = std::max(0.f, n.dot(open_view.direction[l]));
            all += open_view.gain[l] * cosine;
            seen += units.gain[l] * cosine;
          }
          if (seen < 0.5f * all) flags |= kShadowed;
        }
        const Eigen::Vector3f nc = to_camera * n;
        std::copy(n.data(), n.data() + 3, m.diffuse_normal_world.at(x, y));
        std::copy(nc.data(), nc.data() + 3, m.diffuse_normal_camera.at(x, y));
        std::copy(diffuse.rho.data(), diffuse.rho.data() + 3, m.albedo.at(x, y));
        m.fit_residual.at(x, y)[0] = diffuse.chi2;
        m.confidence.at(x, y)[0] =
            internal::Confidence(full_on, static_cast<float>(g), static_cast<float>(read_dn2), diffuse.chi2, flags);
        m.flags[i] = flags;
      }
    }
  });

  internal::RegularizeSpecular(options.specular_filter_radius, options.threads, to_camera, &m);
  return m;
}

}  // namespace stage::processing
