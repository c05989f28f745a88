// The face template (with its shape and expression model) fitted to the simulator's performers through the default
// performance, on their true surfaces (multi-view stereo's meshes: stage_mvs_integration_test and the demo), tracked
// frame to frame from the head at the stage's origin, and each fit measured against where every template vertex belongs
// (through the head's UV layout): docs/assets.md#the-fit.
#include <cstdio>

#include "gtest/gtest.h"
#include "stage/processing/face_template.h"
#include "stage/processing/template_fit.h"
#include "stage/sim/head.h"

namespace stage::processing {
namespace {

struct Worst {
  double surface = 0, rmse = 0, p99 = 0, sliding = 0, matched_rms = 0;
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
        "%.3f); eyes %.3f, mouth %.3f mm; %lld matched at %.3f mm rms; scale %.3f, jaw %.1f deg, largest identity "
        "coefficient %.2f\n",
        static_cast<unsigned long long>(identity), t, e->skin.rmse_mm, e->skin.p99_mm, e->skin.surface_rmse_mm,
        e->skin.sliding_rmse_mm, e->skin.sliding_p99_mm, e->eyes.rmse_mm, e->mouth.rmse_mm,
        static_cast<long long>(fit->matched), fit->rms_mm, fit->scale, fit->jaw_rad * 180 / 3.14159265358979,
        fit->identity.empty() ? 0.0f
                              : *std::max_element(fit->identity.begin(), fit->identity.end(),
                                                  [](float a, float b) { return std::abs(a) < std::abs(b); }));
    EXPECT_GT(fit->matched, static_cast<int64_t>(face.mesh.positions.size() * 9 / 10));
    worst.surface = std::max(worst.surface, e->skin.surface_rmse_mm);
    worst.rmse = std::max(worst.rmse, e->skin.rmse_mm);
    worst.p99 = std::max(worst.p99, e->skin.p99_mm);
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
  // The shipped head (the template's own) and two other performers, none of them among the performers the template's
  // model was made from. Measured (worst frame, 2026-11-29): 0.012, 0.24 and 0.08 mm from where the vertices belong,
  // almost all of it sliding along the surface; without the model (model_iterations 0) 1.8, 5.0 and 4.0 mm of
  // sliding. Issue 28's goals: RMSE <= 0.5 mm, 99th percentile <= 2 mm, sliding <= 1 mm.
  for (uint64_t identity : {0, 5, 7}) {
    const Worst w = TrackPerformer(*face, identity);
    EXPECT_LT(w.matched_rms, 0.05) << identity;
    EXPECT_LT(w.surface, 0.05) << identity;
    EXPECT_LT(w.rmse, 0.4) << identity;
    EXPECT_LT(w.p99, 0.8) << identity;
    EXPECT_LT(w.sliding, 0.4) << identity;
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
