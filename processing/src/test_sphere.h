// Tests: an analytic sphere under the shipped rig's light, made in closed form from the light model (a Lambertian
// sphere, with or without a GGX specular lobe, seen orthographically from +z), and its errors against the truth.
#pragma once

#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "stage/common/ggx.h"
#include "stage/processing/light_model.h"
#include "stage/processing/photometric.h"
#include "stage/processing/take_frames.h"

namespace stage::processing {

struct Sphere {
  std::vector<Image> frames;
  std::vector<Eigen::Vector3d> normals;  // per pixel; zero outside
  PhotometricCamera camera;
  double specular = 0;
  int size = 0;
};

inline const Eigen::Vector3d kAlbedo(0.6, 0.45, 0.35);
constexpr double kRoughness = 0.3, kLeak = 0.01;

// The specular image (per channel, per unit of white_scale) of a GGX lobe with normal n seen from +z under pattern p:
// 2 pi rho_s sum_l w_p(l) I_l D(h) G1(l) G1(v) / (4 n.v) over the units in front (the simulator's BRDF, the diffuse
// with its 1/pi taken out).
inline double SpecularShade(const LightModel& light, int p, const Eigen::Vector3d& n, double rho) {
  const Eigen::Vector3d v = Eigen::Vector3d::UnitZ();
  const double nv = n.dot(v);
  double sum = 0;
  for (size_t l = 0; l < light.directions.size(); ++l) {
    const Eigen::Vector3d& w = light.directions[l];
    const double nw = n.dot(w);
    if (nw <= 0) continue;
    const Eigen::Vector3d h = (w + v).normalized();
    sum += light.patterns[static_cast<size_t>(p)].weights[l] * light.intensity[l] *
           GgxDistribution(static_cast<float>(n.dot(h)), kRoughness) * SmithG1(static_cast<float>(nw), kRoughness) *
           SmithG1(static_cast<float>(nv), kRoughness) / (4 * nv);
  }
  return 2 * M_PI * rho * sum;
}

// A sphere filling `size` x `size` pixels, seen orthographically from +z (its normal at pixel (x, y) is (sx, -sy,
// sqrt(1 - sx^2 - sy^2)) with sx, sy in [-1, 1]; image y runs down), with a lobe of intensity `specular` (0: none).
// Full-on white reads `white_full_e` electrons.
inline Sphere MakeSphere(const LightModel& light, int size, bool noisy, double specular, double white_full_e = 4000) {
  Sphere s;
  s.size = size;
  s.specular = specular;
  // Calibrated so that a white patch facing +z under cross full-on reads white_full_e electrons; 12-bit, full well
  // 10000 e-.
  const double full =
      light.DiffuseVector(*light.Find("cross-full"), Eigen::Vector3d::UnitZ()).dot(Eigen::Vector3d::UnitZ());
  s.camera.gain_e_per_dn = 10000.0 / 4095.0;
  s.camera.white_scale = white_full_e / s.camera.gain_e_per_dn / full;
  s.camera.read_noise_e = 5;
  s.camera.saturation_dn = 4095;
  s.camera.world_to_camera = Eigen::Vector3d(1, -1, -1).asDiagonal();  // looking down -z from +z, y down
  s.camera.cross_leak = kLeak;
  s.frames.assign(light.patterns.size(), Image(size, size, 3));
  s.normals.assign(static_cast<size_t>(size) * size, Eigen::Vector3d::Zero());
  std::mt19937 rng(7);
  std::normal_distribution<double> gauss(0, 1);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double sx = (x + 0.5) / size * 2 - 1, sy = -((y + 0.5) / size * 2 - 1);
      const double r2 = sx * sx + sy * sy;
      if (r2 >= 0.98) continue;
      const Eigen::Vector3d n(sx, sy, std::sqrt(1 - r2));
      s.normals[static_cast<size_t>(y) * size + x] = n;
      for (size_t p = 0; p < light.patterns.size(); ++p) {
        const double shade = n.dot(light.DiffuseVector(static_cast<int>(p), n));
        const double spec = specular > 0 ? SpecularShade(light, static_cast<int>(p), n, specular) *
                                               (light.patterns[p].parallel ? 1 : kLeak)
                                         : 0.0;
        for (int c = 0; c < 3; ++c) {
          double dn = s.camera.white_scale * (kAlbedo[c] * shade + spec);
          if (noisy) {
            const double e = dn * s.camera.gain_e_per_dn;
            dn = std::round((e + std::sqrt(e + 25.0) * gauss(rng)) / s.camera.gain_e_per_dn);
          }
          s.frames[p].at(x, y)[c] = static_cast<float>(std::clamp(dn, 0.0, 4095.0));
        }
      }
    }
  }
  return s;
}

struct Errors {
  double mean_deg = 0, max_deg = 0, albedo_rel = 0;
  int pixels = 0;
  // Specular normal (degrees), intensity (relative) and roughness (absolute), over the pixels with a lobe.
  double specular_deg = 0, specular_rel = 0, roughness_abs = 0;
  int specular_pixels = 0;
  // Pixels whose mirror direction has a unit within 10 degrees, and how many of those have a lobe.
  int mirrored = 0, mirrored_with_lobe = 0;
};

inline Errors Measure(const LightModel& light, const Sphere& s, const PhotometricMaps& m, double max_tilt_deg) {
  Errors e;
  for (int y = 0; y < s.size; ++y) {
    for (int x = 0; x < s.size; ++x) {
      const Eigen::Vector3d& truth = s.normals[static_cast<size_t>(y) * s.size + x];
      if (truth.isZero() || AngleDeg(truth, Eigen::Vector3d::UnitZ()) > max_tilt_deg) continue;
      const float* n = m.diffuse_normal_world.at(x, y);
      const double err = AngleDeg(truth, Eigen::Vector3d(n[0], n[1], n[2]));
      e.mean_deg += err;
      e.max_deg = std::max(e.max_deg, err);
      const float* a = m.albedo.at(x, y);
      for (int c = 0; c < 3; ++c) e.albedo_rel += std::abs(a[c] / kAlbedo[c] - 1) / 3;
      ++e.pixels;
      const float* ns = m.specular_normal_world.at(x, y);
      const bool lobe = !(ns[0] == 0 && ns[1] == 0 && ns[2] == 0);
      const Eigen::Vector3d mirror = 2 * truth.z() * truth - Eigen::Vector3d::UnitZ();
      bool near_unit = false;
      for (const Eigen::Vector3d& d : light.directions) near_unit |= AngleDeg(mirror, d) < 10;
      e.mirrored += near_unit;
      e.mirrored_with_lobe += near_unit && lobe;
      if (!lobe || s.specular == 0) continue;
      e.specular_deg += AngleDeg(truth, Eigen::Vector3d(ns[0], ns[1], ns[2]));
      e.specular_rel += std::abs(m.specular.at(x, y)[0] / s.specular - 1);
      e.roughness_abs += std::abs(m.roughness.at(x, y)[0] - kRoughness);
      ++e.specular_pixels;
    }
  }
  e.mean_deg /= std::max(1, e.pixels);
  e.albedo_rel /= std::max(1, e.pixels);
  e.specular_deg /= std::max(1, e.specular_pixels);
  e.specular_rel /= std::max(1, e.specular_pixels);
  e.roughness_abs /= std::max(1, e.specular_pixels);
  return e;
}

inline void Print(const char* label, const Errors& e) {
  std::printf(
      "%s: diffuse normal mean %.3f deg (max %.3f), albedo %.3f %% over %d pixels; specular normal %.3f deg, "
      "intensity %.2f %%, roughness %.4f over %d pixels (%d of %d whose mirror direction meets a unit)\n",
      label, e.mean_deg, e.max_deg, 100 * e.albedo_rel, e.pixels, e.specular_deg, 100 * e.specular_rel, e.roughness_abs,
      e.specular_pixels, e.mirrored_with_lobe, e.mirrored);
}

// The sphere as a Bayer sensor (RGGB, 12-bit) records it: each pixel keeps the colour it measures.
inline CycleFrames ToMosaic(const Sphere& s) {
  CycleFrames c;
  c.width = c.height = s.size;
  c.bits = 12;
  c.camera_id = "sphere";
  for (const Image& image : s.frames) {
    std::vector<uint16_t> raw(static_cast<size_t>(s.size) * s.size);
    for (int y = 0; y < s.size; ++y) {
      for (int x = 0; x < s.size; ++x) {
        raw[static_cast<size_t>(y) * s.size + x] =
            static_cast<uint16_t>(std::lround(std::clamp(image.at(x, y)[c.mosaic.Color(x, y)], 0.f, 4095.f)));
      }
    }
    c.raw.push_back(std::move(raw));
  }
  return c;
}

// Every map and flag of two solves, byte for byte.
inline void ExpectSameMaps(const PhotometricMaps& one, const PhotometricMaps& other) {
  const std::pair<const char*, Image PhotometricMaps::*> maps[] = {
      {"diffuse_normal_world", &PhotometricMaps::diffuse_normal_world},
      {"diffuse_normal_camera", &PhotometricMaps::diffuse_normal_camera},
      {"albedo", &PhotometricMaps::albedo},
      {"specular_normal_world", &PhotometricMaps::specular_normal_world},
      {"specular_normal_camera", &PhotometricMaps::specular_normal_camera},
      {"specular_normal_raw", &PhotometricMaps::specular_normal_raw},
      {"specular", &PhotometricMaps::specular},
      {"roughness", &PhotometricMaps::roughness},
      {"specular_sigma", &PhotometricMaps::specular_sigma},
      {"confidence", &PhotometricMaps::confidence},
      {"fit_residual", &PhotometricMaps::fit_residual}};
  for (const auto& [name, map] : maps) {
    const std::vector<float>& a = (one.*map).pixels;
    const std::vector<float>& b = (other.*map).pixels;
    ASSERT_EQ(a.size(), b.size()) << name;
    size_t differ = 0;
    for (size_t i = 0; i < a.size(); ++i) differ += std::memcmp(&a[i], &b[i], sizeof(float)) != 0;
    EXPECT_EQ(differ, 0u) << name;
  }
  EXPECT_EQ(one.flags, other.flags);
}

}  // namespace stage::processing
