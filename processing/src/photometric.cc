// Photometric stereo under spherical gradient illumination: see photometric.h.
#include "stage/processing/photometric.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"

namespace stage::processing {
namespace {

struct Twins {
  std::vector<int> cross, parallel;                          // the same gradient under either polarization, paired
  int full = -1;                                             // index into cross/parallel of the full-on pattern
  int xp = -1, xm = -1, yp = -1, ym = -1, zp = -1, zm = -1;  // first-order gradients (for the first guess)
};

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

// Runs body(y0, y1) over row bands on the machine's cores.
template <typename F>
void ParallelRows(int height, F body) {
  const int threads = std::max(1u, std::min(8u, std::thread::hardware_concurrency()));
  std::vector<std::thread> pool;
  const int band = (height + threads - 1) / threads;
  for (int t = 0; t < threads; ++t) {
    const int y0 = t * band, y1 = std::min(height, y0 + band);
    if (y0 >= y1) break;
    pool.emplace_back([=] { body(y0, y1); });
  }
  for (auto& th : pool) th.join();
}

}  // namespace

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) * 180.0 / M_PI;
}

absl::StatusOr<PhotometricMaps> SolvePhotometric(const LightModel& light, const std::vector<Image>& frames,
                                                 const PhotometricCamera& camera, const PhotometricOptions& options,
                                                 const Image* positions) {
  if (frames.size() != light.patterns.size()) {
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
  auto twins = PairPatterns(light);
  if (!twins.ok()) return twins.status();
  const Twins& t = *twins;
  const int np = static_cast<int>(t.cross.size());
  const DiffuseTable table(light, t.cross, options.table_size);

  PhotometricMaps m;
  m.width = w;
  m.height = h;
  m.diffuse_normal_world = Image(w, h, 3);
  m.diffuse_normal_camera = Image(w, h, 3);
  m.albedo = Image(w, h, 3);
  m.confidence = Image(w, h, 1);
  m.fit_residual = Image(w, h, 1);
  m.flags.assign(static_cast<size_t>(w) * h, 0);

  const double k_leak = camera.cross_leak / std::max(1e-9, 1 - camera.cross_leak);
  const double g = camera.gain_e_per_dn;
  const double read_dn2 = 3 * (camera.read_noise_e / g) * (camera.read_noise_e / g);  // three channels summed
  const Eigen::Matrix3f to_camera = camera.world_to_camera.cast<float>();

  ParallelRows(h, [&](int y0, int y1) {
    std::vector<float> c(static_cast<size_t>(np) * 3), d(np), hp(static_cast<size_t>(np) * 3), wt(np);
    // H_p(n) of every cross pattern into hp: from the table, or exactly at the pixel's surface point.
    auto lookup = [&](int x, int y, const Eigen::Vector3f& n) {
      if (positions == nullptr) {
        table.Lookup(n, hp.data());
        return;
      }
      const float* pos = positions->at(x, y);
      const Eigen::Vector3d at(pos[0], pos[1], pos[2]);
      for (int p = 0; p < np; ++p) {
        const Eigen::Vector3d v = light.DiffuseVectorAt(t.cross[p], n.cast<double>(), at);
        for (int k = 0; k < 3; ++k) hp[static_cast<size_t>(p) * 3 + k] = static_cast<float>(v[k]);
      }
    };
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        uint8_t flags = 0;
        // Diffuse per pattern and channel: the cross image less the leaked specular (parallel - cross is specular).
        for (int p = 0; p < np; ++p) {
          const float* cr = frames[static_cast<size_t>(t.cross[p])].at(x, y);
          const float* pa = frames[static_cast<size_t>(t.parallel[p])].at(x, y);
          float sum = 0;
          for (int ch = 0; ch < 3; ++ch) {
            if (cr[ch] >= camera.saturation_dn || pa[ch] >= camera.saturation_dn) flags |= kSaturated;
            const float v = cr[ch] - static_cast<float>(k_leak) * (pa[ch] - cr[ch]);
            c[static_cast<size_t>(p) * 3 + ch] = v;
            sum += v;
          }
          d[p] = sum;
        }
        if (d[t.full] < options.min_signal_dn) {
          m.flags[i] = flags | kLowSignal;
          continue;
        }
        // First guess: the gradients' differences (exact on a full sphere of light); else facing the camera.
        Eigen::Vector3f n(0, 0, 1);
        if (t.xp >= 0 && t.xm >= 0 && t.yp >= 0 && t.ym >= 0 && t.zp >= 0 && t.zm >= 0) {
          const Eigen::Vector3f guess(d[t.xp] - d[t.xm], d[t.yp] - d[t.ym], d[t.zp] - d[t.zm]);
          if (guess.norm() > 1e-6f) n = guess.normalized();
        } else {
          n = (camera.position_mm.cast<float>()).normalized();
        }
        Eigen::Vector3f u = n;
        float chi2 = 0;
        bool solved = false;
        for (int it = 0; it < std::max(1, options.iterations); ++it) {
          lookup(x, y, n);
          Eigen::Matrix3f a = Eigen::Matrix3f::Zero();
          Eigen::Vector3f b = Eigen::Vector3f::Zero();
          for (int p = 0; p < np; ++p) {
            const Eigen::Map<const Eigen::Vector3f> hv(&hp[static_cast<size_t>(p) * 3]);
            const Eigen::Vector3f hs = hv * static_cast<float>(camera.white_scale);
            // The variance at the level the model predicts (the measured level on the first pass).
            const float level = solved ? std::max(0.f, u.dot(hs)) : std::max(0.f, d[p]);
            wt[p] = 1.f / (level / static_cast<float>(g) + static_cast<float>(read_dn2));
            a += wt[p] * hs * hs.transpose();
            b += wt[p] * d[p] * hs;
          }
          const Eigen::Vector3f next = a.ldlt().solve(b);
          if (!next.allFinite() || next.norm() < 1e-9f) break;
          u = next;
          n = u.normalized();
          solved = true;
        }
        if (!solved) {
          m.flags[i] = flags | kLowSignal;
          continue;
        }
        // Per-channel albedo with the normal fixed, and the fit's residual.
        lookup(x, y, n);
        float s2 = 0;
        Eigen::Vector3f rho_num = Eigen::Vector3f::Zero();
        for (int p = 0; p < np; ++p) {
          const Eigen::Map<const Eigen::Vector3f> hv(&hp[static_cast<size_t>(p) * 3]);
          const float s = static_cast<float>(camera.white_scale) * n.dot(hv);
          const float level = std::max(0.f, u.dot(hv) * static_cast<float>(camera.white_scale));
          wt[p] = 1.f / (level / static_cast<float>(g) + static_cast<float>(read_dn2));
          s2 += wt[p] * s * s;
          for (int ch = 0; ch < 3; ++ch) rho_num[ch] += wt[p] * c[static_cast<size_t>(p) * 3 + ch] * s;
          const float r = d[p] - level;
          chi2 += wt[p] * r * r;
        }
        chi2 /= std::max(1, np - 3);
        const Eigen::Vector3f rho = rho_num / std::max(1e-12f, s2);
        if (chi2 > 4) flags |= kBadFit;
        const Eigen::Vector3f nc = to_camera * n;
        std::copy(n.data(), n.data() + 3, m.diffuse_normal_world.at(x, y));
        std::copy(nc.data(), nc.data() + 3, m.diffuse_normal_camera.at(x, y));
        std::copy(rho.data(), rho.data() + 3, m.albedo.at(x, y));
        m.fit_residual.at(x, y)[0] = chi2;
        // Confidence: signal (the full-on's SNR, 1 at 100), times the fit's agreement, zero when clipped.
        const float snr = d[t.full] / std::sqrt(d[t.full] / static_cast<float>(g) + static_cast<float>(read_dn2));
        float conf = std::min(1.f, snr / 100.f) * std::exp(-std::max(0.f, chi2 - 2.f) / 4.f);
        if (flags & kSaturated) conf = 0;
        m.confidence.at(x, y)[0] = conf;
        m.flags[i] = flags;
      }
    }
  });
  return m;
}

}  // namespace stage::processing
