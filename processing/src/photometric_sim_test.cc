// Photometric stereo on the simulated stage: a subject as hs-2 records it (12-bit Bayer), rendered by the simulator in
// process, demosaiced as the pipeline does, solved with the camera as the pipeline resolves it (calibration.h), and
// compared with the ground truth of the same pixels (the shading normal, albedo, specular intensity and roughness the
// renderer used; with sim.supersample, the mean over the pixel's rays, as the sensor integrates them). On the
// simulator's sphere with (almost) no noise the solver's model must match the renderer's exactly once the geometry is
// known; on the procedural head (full-on 4000 e- for white, read noise 5 e-, 12-bit, 3 x 3 rays a pixel) the goals of
// issue #6 are checked with the geometry known (the simulator's own: where each pixel lands and what it sees, as
// multi-view stereo will give it).
#include <algorithm>
#include <cstdio>
#include <cstdlib>

#include "gtest/gtest.h"
#include "photometric_internal.h"
#include "rendered_cycle.h"
#include "stage/common/rig.h"
#include "stage/processing/calibration.h"
#include "stage/processing/photometric.h"
#include "stage/processing/take_frames.h"
#include "stage/sim/light_transport.h"
#include "stage/sim/scene.h"

namespace stage::processing {
namespace {

struct Stat {
  double mean = 0, median = 0, p90 = 0;
  size_t pixels = 0;
};

Stat Summarize(std::vector<double> v) {
  Stat s;
  s.pixels = v.size();
  if (v.empty()) return s;
  for (double e : v) s.mean += e;
  s.mean /= static_cast<double>(v.size());
  std::sort(v.begin(), v.end());
  s.median = v[v.size() / 2];
  s.p90 = v[v.size() * 9 / 10];
  return s;
}

struct Result {
  Stat diffuse, specular, specular_raw, albedo, rho, roughness;
  // The albedo's relative error in the channel each Bayer pixel measures (RGGB), and in the two it interpolates.
  double albedo_measured = 0, albedo_interpolated = 0;
  // The share of the measured lobes whose raw fit is off by more than 3 times the standard deviation the fit gives
  // itself (specular_sigma, over both tangent axes): its own account of its noise, which the regularization weighs it
  // by. For an honest Gaussian fit about exp(-9) = 0.012 %; the model's own errors (the mosaic, the pixel's
  // footprint) add to that.
  double lobes_beyond_3_sigma = 0;
};

// Which channel pixel (x, y) of an RGGB mosaic measures.
int BayerChannel(int x, int y) { return (y % 2 == 0) ? (x % 2 == 0 ? 0 : 1) : (x % 2 == 0 ? 1 : 2); }

// Errors on the skin (part 0; the sphere is all part 0).
Result Evaluate(const RenderedCycle& r, const PhotometricMaps& maps) {
  std::vector<double> diffuse, specular, raw, albedo, rho, rough;
  double measured = 0, interpolated = 0, beyond = 0;
  for (int y = 0; y < maps.height; ++y) {
    for (int x = 0; x < maps.width; ++x) {
      const sim::Hit& hit = r.hits[static_cast<size_t>(y) * maps.width + x];
      if (!hit.hit || hit.part != 0) continue;
      const float* n = maps.diffuse_normal_world.at(x, y);
      if (n[0] == 0 && n[1] == 0 && n[2] == 0) continue;
      const Eigen::Vector3d truth = hit.normal.cast<double>();
      diffuse.push_back(AngleDeg(truth, Eigen::Vector3d(n[0], n[1], n[2])));
      const float* a = maps.albedo.at(x, y);
      double rel = 0;
      for (int c = 0; c < 3; ++c) {
        const double e = std::abs(a[c] / hit.material.albedo[c] - 1);
        rel += e / 3;
        if (c == BayerChannel(x, y)) {
          measured += e;
        } else {
          interpolated += e / 2;
        }
      }
      albedo.push_back(rel);
      const float* s = maps.specular_normal_world.at(x, y);
      if (s[0] == 0 && s[1] == 0 && s[2] == 0) continue;
      specular.push_back(AngleDeg(truth, Eigen::Vector3d(s[0], s[1], s[2])));
      const float* sr = maps.specular_normal_raw.at(x, y);
      raw.push_back(AngleDeg(truth, Eigen::Vector3d(sr[0], sr[1], sr[2])));
      beyond += raw.back() > 3 * maps.specular_sigma.at(x, y)[0];
      rho.push_back(std::abs(maps.specular.at(x, y)[0] / hit.material.specular - 1));
      rough.push_back(std::abs(maps.roughness.at(x, y)[0] - hit.material.roughness));
    }
  }
  const double n = static_cast<double>(std::max<size_t>(1, albedo.size()));
  return {Summarize(diffuse), Summarize(specular), Summarize(raw),
          Summarize(albedo),  Summarize(rho),      Summarize(rough),
          measured / n,       interpolated / n,    beyond / static_cast<double>(std::max<size_t>(1, raw.size()))};
}

void Print(const std::string& label, const Result& r) {
  std::printf(
      "%s (%zu pixels):\n  diffuse normal mean %.2f median %.2f p90 %.2f deg; albedo %.2f %%\n"
      "  specular normal mean %.2f median %.2f p90 %.2f deg (raw fit mean %.2f median %.2f) over %zu pixels;\n"
      "  specular intensity mean %.1f %% median %.1f %%; roughness mean abs %.3f median %.3f\n"
      "  albedo in the channel each pixel measures %.2f %%, in the two it interpolates %.2f %%\n"
      "  lobes whose raw fit is off by more than 3 times its own standard deviation %.2f %%\n",
      label.c_str(), r.diffuse.pixels, r.diffuse.mean, r.diffuse.median, r.diffuse.p90, 100 * r.albedo.mean,
      r.specular.mean, r.specular.median, r.specular.p90, r.specular_raw.mean, r.specular_raw.median, r.specular.pixels,
      100 * r.rho.mean, 100 * r.rho.median, r.roughness.mean, r.roughness.median, 100 * r.albedo_measured,
      100 * r.albedo_interpolated, 100 * r.lobes_beyond_3_sigma);
}

// Solves the rendered cycle with the units seen from the dome's centre (far; skipped where far_result is null) and
// with the geometry known (near), and prints both against the truth.
void SolveFarAndNear(const RenderedCycle& r, const std::string& subject, Result* far_result, Result* near_result,
                     PhotometricMaps* near_maps = nullptr) {
  if (far_result != nullptr) {
    auto far = SolvePhotometric(r.light, r.frames, r.camera);
    ASSERT_TRUE(far.ok()) << far.status();
    *far_result = Evaluate(r, *far);
    Print(subject + ", units from the dome's centre", *far_result);
  }
  auto near = SolvePhotometric(r.light, r.frames, r.camera, {}, &r.truth_geometry);
  ASSERT_TRUE(near.ok()) << near.status();
  *near_result = Evaluate(r, *near);
  Print(subject + ", geometry known", *near_result);
  if (near_maps != nullptr) *near_maps = std::move(*near);
}

// The simulator's sphere (100 mm, no self-shadowing) with noise made negligible: the solver's model is the renderer's.
TEST(PhotometricSimTest, OnTheRenderedSphereTheModelIsTheRenderers) {
  RenderedCycle r;
  ASSERT_NO_FATAL_FAILURE(RenderCycle(
      "hs-2",
      {"sim.subject.kind=sphere", "sim.full_on_electrons=1000000", "sim.full_well_e=2500000", "sim.read_noise_e=0.1"},
      &r));
  Result rf, rn;
  ASSERT_NO_FATAL_FAILURE(SolveFarAndNear(r, "sphere", &rf, &rn));
  EXPECT_GT(rn.diffuse.pixels, 20000u);
  EXPECT_LT(rn.diffuse.mean, 0.3);
  EXPECT_LT(rn.albedo.mean, 0.01);
  // From the dome's centre the units' real distance (the sphere's surface is 100 mm from it) costs degrees.
  EXPECT_GT(rf.diffuse.mean, 1.0);
}

// The photon-noise bound of the albedo in the channel each pixel measures: the diffuse electrons of that channel in
// both polarizations (twice the cross images), summed over the patterns; an unbiased estimate of a Poisson scale from
// N electrons errs by 1/sqrt(N) relative, a mean absolute error of sqrt(2/pi)/sqrt(N). Mean over the skin pixels the
// solver solved.
double AlbedoPhotonBound(const RenderedCycle& r, const PhotometricMaps& maps) {
  auto twins = internal::PairPatterns(r.light);
  EXPECT_TRUE(twins.ok()) << twins.status();
  if (!twins.ok()) return 0;
  double sum = 0;
  size_t n = 0;
  for (int y = 0; y < maps.height; ++y) {
    for (int x = 0; x < maps.width; ++x) {
      const sim::Hit& hit = r.hits[static_cast<size_t>(y) * maps.width + x];
      const float* a = maps.albedo.at(x, y);
      if (!hit.hit || hit.part != 0 || (a[0] == 0 && a[1] == 0 && a[2] == 0)) continue;
      double electrons = 0;
      for (int p : twins->cross) {
        electrons += 2 * r.frames[static_cast<size_t>(p)].at(x, y)[BayerChannel(x, y)] * r.camera.gain_e_per_dn;
      }
      if (electrons <= 0) continue;
      sum += std::sqrt(2 / internal::kPi) / std::sqrt(electrons);
      ++n;
    }
  }
  return n > 0 ? sum / static_cast<double>(n) : 0;
}

// Issue #6's goals on the procedural head, as hs-2 sees it (12-bit, 3 x 3 rays a pixel), with the geometry known:
// diffuse normals <= 1.5 deg, specular normals <= 5 deg where a lobe is measured, roughness <= 0.05. The albedo is at
// 1.06 % (goal 0.7 %). Each Bayer pixel measures one channel: there it errs by 0.9 %, against a photon-noise bound of
// about 0.5 % for skin at 4000 e- for white (and 0.45 % with no noise at all, from the demosaiced neighbours' share in
// the normal); the two channels it interpolates take the pixel's own texture and its neighbours' hue
// (internal::DemosaicAlbedo): 1.13 %, against 2.0 % from the neighbours alone.
// Without the geometry (units from the dome's centre) the normals are 5 deg off: the units' real distance and the
// head's own shadows matter.
TEST(PhotometricSimTest, TheProceduralHeadAgainstGroundTruth) {
  RenderedCycle r;
  ASSERT_NO_FATAL_FAILURE(RenderCycle("hs-2", {"sim.supersample=3"}, &r));
  Result rf, rn;
  PhotometricMaps near;
  ASSERT_NO_FATAL_FAILURE(SolveFarAndNear(r, "head", &rf, &rn, &near));
  EXPECT_GT(rn.diffuse.pixels, 40000u);
  EXPECT_LT(rn.diffuse.mean, 1.5);
  EXPECT_LT(rn.albedo.mean, 0.012);
  // The interpolated channels within 1.3x of the measured one (2.2x from the neighbours alone).
  EXPECT_LT(rn.albedo_interpolated, 1.3 * rn.albedo_measured);
  EXPECT_GT(rn.specular.pixels, rn.diffuse.pixels / 5);
  EXPECT_LT(rn.specular.mean, 5);
  EXPECT_LT(rn.roughness.mean, 0.05);
  EXPECT_GT(rf.diffuse.mean, 3 * rn.diffuse.mean);
  // The lobe fits' own standard deviations hold (0.09 %; 0.75 % when a near-singular fit's variance, inverted in
  // float, could come out as zero: the worst fits, 20-40 deg off, passed as the surest).
  EXPECT_LT(rn.lobes_beyond_3_sigma, 0.003);
  // The measured channel, beside what photon noise allows.
  const double bound = AlbedoPhotonBound(r, near);
  std::printf("head, geometry known: albedo photon-noise bound in the measured channel %.2f %% (measured %.2f %%)\n",
              100 * bound, 100 * rn.albedo_measured);
  EXPECT_GT(bound, 0.003);
  EXPECT_LT(rn.albedo_measured, 0.01);
  EXPECT_GT(rn.albedo_measured, bound);  // no estimate beats the photon noise: a check on the test's own figures
}

// The same head with photon and read noise made negligible (250 times the light): what is left is the model's error
// and the Bayer mosaic's. The albedo errs by 0.75 % here: 0.45 % in the channel each pixel measures (the demosaiced
// neighbours' share in the normal its shading is computed with) and 0.90 % in the two it interpolates (its neighbours'
// hue, with their own error). That is above issue #6's 0.7 % before any noise is added (docs/processing.md#accuracy).
// The bounds guard these systematic errors apart from the noise.
TEST(PhotometricSimTest, TheProceduralHeadWithoutNoise) {
  RenderedCycle r;
  ASSERT_NO_FATAL_FAILURE(RenderCycle(
      "hs-2", {"sim.supersample=3", "sim.full_on_electrons=1000000", "sim.full_well_e=2500000", "sim.read_noise_e=0.1"},
      &r));
  Result rn;
  ASSERT_NO_FATAL_FAILURE(SolveFarAndNear(r, "head without noise", nullptr, &rn));
  EXPECT_GT(rn.diffuse.pixels, 40000u);
  EXPECT_LT(rn.diffuse.mean, 1.0);
  EXPECT_LT(rn.albedo.mean, 0.009);
  EXPECT_LT(rn.albedo_measured, 0.006);
  EXPECT_LT(rn.albedo_interpolated, 0.011);
  EXPECT_LT(rn.specular.mean, 2.5);
  EXPECT_LT(rn.roughness.mean, 0.025);
}

}  // namespace
}  // namespace stage::processing
