// The face template fitted to the simulator's performers through the default performance, on their true surfaces
// (multi-view stereo's meshes come later), tracked frame to frame from the head at the stage's origin, and each fit
// measured against where every template vertex belongs (through the head's UV layout): docs/assets.md#the-fit.
#include <cstdio>

#include "gtest/gtest.h"
#include "stage/processing/face_template.h"
#include "stage/processing/template_fit.h"
#include "stage/sim/head.h"

namespace stage::processing {
namespace {

struct Worst {
  double surface = 0, rmse = 0, sliding = 0, matched_rms = 0;
};

// The performance at 0.5 s steps, each frame's fit starting from the one before.
Worst TrackPerformer(const FaceTemplate& face, uint64_t identity) {
  const auto performer = sim::HeadModel::Procedural(1, 256, sim::HeadShape::Drawn(identity));
  const sim::Performance performance = sim::Performance::Default();
  TemplateFit previous = StartAt(face, Eigen::Isometry3f::Identity());
  Worst worst;
  for (double t = 0; t < 3.9; t += 0.5) {
    const TriangleMesh truth = performer->PosedMesh(performance.At(t));
    auto fit = FitTemplate(face, truth, previous);
    EXPECT_TRUE(fit.ok()) << fit.status();
    if (!fit.ok()) return worst;
    auto e = EvaluateFit(face, *fit, truth);
    EXPECT_TRUE(e.ok()) << e.status();
    if (!e.ok()) return worst;
    std::printf(
        "identity %llu, t %.1f s: skin rmse %.3f p99 %.3f mm (along the normal %.3f, sliding %.3f, p99 "
        "%.3f); eyes %.3f, mouth %.3f mm; %lld matched at %.3f mm rms; scale %.3f, jaw %.1f deg\n",
        static_cast<unsigned long long>(identity), t, e->skin.rmse_mm, e->skin.p99_mm, e->skin.surface_rmse_mm,
        e->skin.sliding_rmse_mm, e->skin.sliding_p99_mm, e->eyes.rmse_mm, e->mouth.rmse_mm,
        static_cast<long long>(fit->matched), fit->rms_mm, fit->scale, fit->jaw_rad * 180 / 3.14159265358979);
    EXPECT_GT(fit->matched, static_cast<int64_t>(face.mesh.positions.size() * 9 / 10));
    worst.surface = std::max(worst.surface, e->skin.surface_rmse_mm);
    worst.rmse = std::max(worst.rmse, e->skin.rmse_mm);
    worst.sliding = std::max(worst.sliding, e->skin.sliding_rmse_mm);
    worst.matched_rms = std::max(worst.matched_rms, fit->rms_mm);
    previous = *std::move(fit);
  }
  std::printf(
      "identity %llu, worst frame: on the surface %.3f mm (rms to it %.3f), to where it belongs %.3f mm, "
      "sliding %.3f mm\n",
      static_cast<unsigned long long>(identity), worst.surface, worst.matched_rms, worst.rmse, worst.sliding);
  return worst;
}

TEST(TemplateFitSimTest, TheFitLiesOnAPerformersSurfaceThroughThePerformance) {
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok()) << face.status();
  // The shipped head (the template's own) and two other performers. Measured (worst frame): the template's
  // vertices 0.11-0.14 mm from the true surface (RMS over the skin) and 0.13-0.24 mm along its normal from where they
  // belong; along the surface they slide 1.8 mm on the template's own head (the jaw opening) and 4-5 mm on the
  // others (their proportions: nothing yet holds a vertex to its skin point but the surface's shape; the issue's
  // goal is 1 mm). Before the jaw's turn was fitted: 5.2, 8.3 and 7.2 mm.
  const std::vector<std::pair<uint64_t, double>> sliding_bounds = {{0, 2.5}, {5, 6.0}, {7, 5.0}};
  for (const auto& [identity, sliding] : sliding_bounds) {
    const Worst w = TrackPerformer(*face, identity);
    EXPECT_LT(w.matched_rms, 0.2) << identity;
    EXPECT_LT(w.surface, 0.35) << identity;
    EXPECT_LT(w.sliding, sliding) << identity;
  }
}

TEST(TemplateFitSimTest, TheTemplateFitsItsOwnHeadExactly) {
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  const auto head = sim::HeadModel::Procedural(1);
  // The head moved off the template's pose by a few millimetres and degrees: the fit finds it and the face.
  sim::HeadPose pose;
  pose.rotation_deg = {4, -3, 2};
  pose.translation_mm = {3, -2, 4};
  const TriangleMesh truth = head->PosedMesh(pose);
  auto fit = FitTemplate(*face, truth, StartAt(*face, Eigen::Isometry3f::Identity()));
  ASSERT_TRUE(fit.ok()) << fit.status();
  auto e = EvaluateFit(*face, *fit, truth);
  ASSERT_TRUE(e.ok());
  std::printf("its own head, moved: skin rmse %.4f mm, p99 %.4f, sliding %.4f; scale %.4f\n", e->skin.rmse_mm,
              e->skin.p99_mm, e->skin.sliding_rmse_mm, fit->scale);
  EXPECT_LT(e->skin.rmse_mm, 0.1);
  EXPECT_LT(e->skin.p99_mm, 0.3);
  EXPECT_NEAR(fit->scale, 1, 2e-3);
}

}  // namespace
}  // namespace stage::processing
