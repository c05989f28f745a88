// The specular regularization (internal::RegularizeSpecular, shared by both solvers) against the one-pixel loop it
// replaced, kept here as the reference: random maps (with NaN normals, pixels without a lobe, runs of background),
// image sizes around the 16-pixel lanes and the window, radii from none to wider than the image, one to seven
// threads, the AVX-512 lanes on and off. The regularized maps must be the reference's bits.
#include <cmath>
#include <cstring>
#include <limits>
#include <random>

#include "gtest/gtest.h"
#include "photometric_internal.h"

namespace stage::processing {
namespace {

// The regularization as one loop per pixel over its window, as it was first written.
void Reference(int radius, const Eigen::Matrix3f& to_camera, PhotometricMaps* maps) {
  PhotometricMaps& m = *maps;
  const int w = m.width, h = m.height;
  const size_t n = static_cast<size_t>(w) * h;
  const float* var_n = internal::Work(&m, internal::kVarNormal);
  const float* var_la = internal::Work(&m, internal::kVarLogAlpha);
  std::vector<float> delta(3 * n), log_alpha(n);
  const float* nd = m.diffuse_normal_world.pixels.data();
  auto has_lobe = [&](size_t i) { return (m.flags[i] & (kLowSignal | kNoSpecular)) == 0; };
  for (size_t i = 0; i < n; ++i) {
    if (!has_lobe(i)) continue;
    for (int k = 0; k < 3; ++k) delta[3 * i + k] = m.specular_normal_raw.pixels[3 * i + k] - nd[3 * i + k];
    log_alpha[i] = internal::PortableLog(m.roughness.pixels[i]);
  }
  std::vector<float> roughness = m.roughness.pixels;
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const size_t i = static_cast<size_t>(y) * w + x;
      float* sw = &m.specular_normal_world.pixels[3 * i];
      float* sc = &m.specular_normal_camera.pixels[3 * i];
      if (!has_lobe(i)) {
        std::fill(sw, sw + 3, 0.f);
        std::fill(sc, sc + 3, 0.f);
        continue;
      }
      const float* n0 = &nd[3 * i];
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
      roughness[i] = internal::PortableExp(la);
    }
  }
  m.roughness.pixels = roughness;
}

// Random maps of w x h: diffuse normals near +z (a few NaN), raw specular normals near them, roughness, noise; most
// pixels with a lobe, some without, a band of background.
PhotometricMaps RandomMaps(int w, int h, uint32_t seed) {
  PhotometricMaps m;
  internal::PrepareMaps(w, h, &m);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1, 1), pos(0.05f, 1.f);
  const size_t n = static_cast<size_t>(w) * h;
  float* var_n = internal::Work(&m, internal::kVarNormal);
  float* var_la = internal::Work(&m, internal::kVarLogAlpha);
  for (size_t i = 0; i < n; ++i) {
    Eigen::Vector3f nd(0.5f * u(rng), 0.5f * u(rng), 1);
    nd.normalize();
    if (rng() % 50 == 0) nd = Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN());
    const Eigen::Vector3f raw = (nd + 0.1f * Eigen::Vector3f(u(rng), u(rng), u(rng))).normalized();
    for (int c = 0; c < 3; ++c) {
      m.diffuse_normal_world.pixels[3 * i + c] = nd[c];
      m.specular_normal_raw.pixels[3 * i + c] = raw[c];
      m.specular_normal_world.pixels[3 * i + c] = u(rng);  // what a previous solve left
    }
    m.roughness.pixels[i] = pos(rng);
    var_n[i] = rng() % 20 == 0 ? 0.f : 0.01f * pos(rng);
    var_la[i] = 0.1f * pos(rng);
    const size_t x = i % static_cast<size_t>(w);
    m.flags[i] = x >= 20 && x < 40 ? kLowSignal : rng() % 4 == 0 ? kNoSpecular : 0;
  }
  return m;
}

void ExpectSameBits(const std::vector<float>& a, const std::vector<float>& b, const std::string& what) {
  ASSERT_EQ(a.size(), b.size()) << what;
  size_t differ = 0;
  for (size_t i = 0; i < a.size(); ++i) differ += std::memcmp(&a[i], &b[i], sizeof(float)) != 0;
  EXPECT_EQ(differ, 0u) << what;
}

TEST(RegularizeSpecularTest, GivesTheOnePixelLoopsBits) {
  Eigen::Matrix3f to_camera;
  to_camera << 0.8f, -0.6f, 0, 0.6f, 0.8f, 0, 0, 0, 1;
  size_t regularized = 0;  // pixels whose roughness the reference changed: the filter did something
  for (const int w : {1, 5, 17, 33, 70}) {
    for (const int h : {1, 3, 40}) {
      for (const int radius : {-1, 0, 1, 2, 9, 80}) {
        PhotometricMaps expected = RandomMaps(w, h, static_cast<uint32_t>(w * 1000 + h));
        const std::vector<float> raw = expected.roughness.pixels;
        Reference(radius, to_camera, &expected);
        for (size_t i = 0; i < raw.size(); ++i) regularized += raw[i] != expected.roughness.pixels[i];
        for (const int threads : {1, 3, 7}) {
          for (const bool lanes : {true, false}) {
            PhotometricMaps m = RandomMaps(w, h, static_cast<uint32_t>(w * 1000 + h));
            internal::FastVectorKernels() = lanes;
            internal::RegularizeSpecular(radius, threads, to_camera, &m);
            internal::FastVectorKernels() = true;
            const std::string what = std::to_string(w) + "x" + std::to_string(h) + " radius " +
                                     std::to_string(radius) + ", " + std::to_string(threads) + " threads" +
                                     (lanes ? ", lanes" : "");
            ExpectSameBits(m.specular_normal_world.pixels, expected.specular_normal_world.pixels, "world " + what);
            ExpectSameBits(m.specular_normal_camera.pixels, expected.specular_normal_camera.pixels, "camera " + what);
            ExpectSameBits(m.roughness.pixels, expected.roughness.pixels, "roughness " + what);
          }
        }
      }
    }
  }
  EXPECT_GT(regularized, 1000u);
}

}  // namespace
}  // namespace stage::processing
