// Temporal stabilization on the simulated stage (docs/assets.md#temporal-stabilization): a performer of other
// proportions than the template's (identity 5) through the default performance at half-second steps; each frame's
// template fitted to the true surface from the frame before without the template's model (so that it slides 4-5 mm
// along the skin, as a fit whose model does not know the performer would), and the
// simulator's true maps of the three high-speed views fused through it. The textures drift with the fit's sliding;
// warped onto the first frame's along the albedo's optical flow they hold still.
#include <algorithm>
#include <cstdio>
#include <cstdlib>

#include "absl/strings/str_format.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/common/uv_raster.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"
#include "stage/processing/stabilize.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/texture_fusion.h"
#include "stage/sim/ground_truth.h"
#include "stage/sim/scene.h"

namespace stage::processing {
namespace {

// The three high-speed views' true maps of virtual frame `frame`, fused through `mesh`.
FusedTextures FuseTruth(const sim::SimScene& scene, int64_t frame, const TriangleMesh& mesh,
                        const Eigen::Isometry3f& head_from_stage, int size) {
  const std::string dir = ::testing::TempDir() + "/stabilize-truth";
  const std::vector<std::string> ids = {"hs-1", "hs-2", "hs-3"};
  EXPECT_TRUE(sim::WriteGroundTruth(scene, dir, {.first_frame = frame, .last_frame = frame + 1, .cameras = ids}).ok());
  std::vector<FusionView> views;
  for (const std::string& id : ids) {
    FusionView v;
    v.camera_id = id;
    v.camera = scene.camera(scene.CameraIndex(id));
    const std::string maps = absl::StrFormat("%s/frame-%06d/%s/", dir, frame, id);
    auto albedo = ReadImageFile(maps + "albedo.exr");
    auto normal = ReadImageFile(maps + "normal_world.exr");
    EXPECT_TRUE(albedo.ok() && normal.ok()) << id;
    if (!albedo.ok() || !normal.ok()) return {};
    v.albedo = *albedo;
    v.diffuse_normal = *normal;
    views.push_back(std::move(v));
  }
  FusionOptions options;
  options.size = size;
  auto fused = FuseTextures(mesh, head_from_stage, views, options);
  EXPECT_TRUE(fused.ok()) << fused.status();
  return fused.ok() ? *std::move(fused) : FusedTextures{};
}

// Where on the truth's skin each of `points` (stage frame, near the truth's surface) lies: the layout uv whose point on
// `truth_map` (MakeGeometryMap of the truth, stage frame) is nearest, by Gauss-Newton from `guess` (where it belongs).
std::vector<Eigen::Vector2f> SkinPointsUnder(const GeometryMap& truth_map, const std::vector<Eigen::Vector3f>& points,
                                             const std::vector<Eigen::Vector2f>& guess) {
  std::vector<Eigen::Vector2f> uvs = guess;
  const float du = 1.0f / static_cast<float>(truth_map.size);
  for (size_t i = 0; i < points.size(); ++i) {
    Eigen::Vector2f uv = guess[i];
    for (int it = 0; it < 20; ++it) {
      const auto p = SampleGeometryMap(truth_map, uv), pu = SampleGeometryMap(truth_map, uv + Eigen::Vector2f(du, 0)),
                 pv = SampleGeometryMap(truth_map, uv + Eigen::Vector2f(0, du));
      if (!p || !pu || !pv) break;
      Eigen::Matrix<float, 3, 2> j;
      j.col(0) = (*pu - *p) / du;
      j.col(1) = (*pv - *p) / du;
      const Eigen::Vector2f step = (j.transpose() * j).ldlt().solve(j.transpose() * (points[i] - *p));
      if (!step.allFinite()) break;
      uv += step.cwiseMax(-8 * du).cwiseMin(8 * du);
      if (step.norm() < 0.01f * du) break;
    }
    uvs[i] = uv;
  }
  return uvs;
}

TEST(StabilizeSimTest, TheFlowAndTheUNetHoldTheTexturesOfASlidingFitStill) {
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok()) << face.status();
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.render_scale=0.125", "sim.subject.identity=5"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto scene = sim::SimScene::FromLoadedRig(*rig);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const sim::HeadModel& head = *(*scene)->head();
  constexpr int kSize = 256;
  const std::vector<int64_t> frames = {0, 12, 24, 36};  // half a second apart at 24 frames a second
  std::vector<FusedTextures> fitted, placed, followed;
  std::vector<sim::HeadPose> poses;
  // The skin points the first frame's fit lies on (the layout's uv of each vertex's point on the truth): the textures
  // stabilized onto that frame's are those points' textures, and `followed` fuses the truth through a template on
  // the same points in every frame, the reference for how much the wrinkles bend there.
  std::vector<Eigen::Vector2f> skin_points;
  TemplateFit previous = StartAt(*face, Eigen::Isometry3f::Identity());
  for (int64_t frame : frames) {
    const sim::HeadPose pose = (*scene)->PoseAt(frame);
    poses.push_back(pose);
    const TriangleMesh truth = head.PosedMesh(pose);
    auto fit = FitTemplate(*face, truth, previous, {.model_iterations = 0});
    ASSERT_TRUE(fit.ok()) << fit.status();
    auto e = EvaluateFit(*face, *fit, truth);
    ASSERT_TRUE(e.ok());
    TriangleMesh mesh = face->mesh;
    mesh.positions = fit->positions;
    fitted.push_back(FuseTruth(**scene, frame, mesh, fit->stage_from_head.inverse(), kSize));
    // The template where it belongs (no sliding), for comparison.
    auto on_truth = TemplateOnTruth(*face, truth);
    ASSERT_TRUE(on_truth.ok());
    placed.push_back(FuseTruth(**scene, frame, *on_truth, fit->stage_from_head.inverse(), kSize));
    auto truth_map = MakeGeometryMap(truth, Eigen::Isometry3f::Identity(), {.size = 2048, .dilation_px = 2});
    ASSERT_TRUE(truth_map.ok()) << truth_map.status();
    if (skin_points.empty()) {
      std::vector<Eigen::Vector2f> belongs;
      for (const Eigen::Vector2f& uv : face->mesh.uvs) belongs.push_back(face->HeadLayoutUv(uv));
      skin_points = SkinPointsUnder(*truth_map, fit->positions, belongs);
      // The points found lie under the fit's vertices (the fit is on the true surface), not where they belong.
      double under = 0, from_belongs = 0;
      size_t found = 0;
      for (size_t v = 0; v < skin_points.size(); ++v) {
        const auto p = SampleGeometryMap(*truth_map, skin_points[v]), q = SampleGeometryMap(*truth_map, belongs[v]);
        if (!p || !q) continue;
        under += (*p - fit->positions[v]).norm();
        from_belongs += (*p - *q).norm();
        ++found;
      }
      ASSERT_GT(found, skin_points.size() * 99 / 100);
      std::printf("skin points under the first fit: %.3f mm from its vertices, %.2f mm from where they belong\n",
                  under / static_cast<double>(found), from_belongs / static_cast<double>(found));
      EXPECT_LT(under / static_cast<double>(found), 0.2);  // measured 0.056 mm (4.2 mm from where they belong)
    }
    TriangleMesh on_points = face->mesh;
    size_t off_layout = 0;  // vertices whose skin point the layout does not cover (kept where the fit has them)
    for (size_t v = 0; v < on_points.positions.size(); ++v) {
      const auto p = SampleGeometryMap(*truth_map, skin_points[v]);
      on_points.positions[v] = p ? *p : fit->positions[v];
      off_layout += !p;
    }
    ASSERT_LT(off_layout * 100, on_points.positions.size()) << frame;
    followed.push_back(FuseTruth(**scene, frame, on_points, fit->stage_from_head.inverse(), kSize));
    std::printf("frame %lld: the fit slides %.2f mm rms along the skin\n", static_cast<long long>(frame),
                e->skin.sliding_rmse_mm);
    previous = *std::move(fit);
  }
  // Still skin: texels whose true albedo (at the skin point the layout puts there) no expression changes.
  std::vector<bool> still(static_cast<size_t>(kSize) * kSize, false);
  for (int y = 0; y < kSize; ++y) {
    for (int x = 0; x < kSize; ++x) {
      const Eigen::Vector2f uv = face->HeadLayoutUv(TexelUv(x, y, kSize));
      const float first = head.Surface(uv, 0, poses[0].expression).material.albedo.y();
      bool same = first > 0;
      for (size_t k = 1; k < poses.size() && same; ++k) {
        same = std::abs(head.Surface(uv, 0, poses[k].expression).material.albedo.y() - first) < 0.005f * first;
      }
      still[static_cast<size_t>(y) * kSize + x] = same;
    }
  }
  // FASTAGE_STABILIZE_TAKE=DIR: the fused textures written as a take's (frames 0-3: DIR/derived/textures; the
  // template where it belongs: DIR/derived/placed), for `stage-process stabilize --take DIR` (the U-Net's figures in
  // docs/assets.md#the-u-net).
  if (const char* take = std::getenv("FASTAGE_STABILIZE_TAKE")) {
    for (size_t k = 0; k < frames.size(); ++k) {
      for (const auto& [dir, t] : {std::pair{"textures", &fitted[k]}, std::pair{"placed", &placed[k]}}) {
        const std::string path = absl::StrFormat("%s/derived/%s/frame-%06d", take, dir, k);
        ASSERT_TRUE(WriteFusedTextures(path, *t, absl::StrFormat("{\"frame\": %d}", frames[k]), "fused").ok()) << path;
      }
    }
  }
  // Both methods, one measure: the jitter on the still skin as fused, stabilized, and with the template where it
  // belongs; the wrinkles' bend kept.
  for (const StabilizeMethod method : {StabilizeMethod::kFlow, StabilizeMethod::kUNet}) {
    StabilizeOptions options;
    options.method = method;
    options.net.threads = 2;
    auto stable = StabilizeSequence(fitted[0], {fitted.begin() + 1, fitted.end()}, options);
    ASSERT_TRUE(stable.ok()) << stable.status();
    std::printf("%s:\n", std::string(StabilizeMethodName(method)).c_str());
    double raw = 0, stabilized = 0, truth = 0;
    FusedTextures before = fitted[0];
    for (size_t k = 1; k < frames.size(); ++k) {
      const StabilizedTextures& s = (*stable)[k - 1];
      const double r = AlbedoJitter(fitted[k - 1], fitted[k], &still);
      const double j = AlbedoJitter(before, s.textures, &still);
      const double t = AlbedoJitter(placed[k - 1], placed[k], &still);
      std::printf(
          "frames %lld-%lld: albedo jitter %.2f %% as fused, %.2f %% stabilized (flow %.2f texels), %.2f %% "
          "with the template where it belongs\n",
          static_cast<long long>(frames[k - 1]), static_cast<long long>(frames[k]), 100 * r, 100 * j, s.mean_flow_px,
          100 * t);
      raw += r;
      stabilized += j;
      truth += t;
      before = s.textures;
      // Wrinkles: where the expression bends the skin's normals since the first frame by more than 2 deg, at the skin
      // points the stabilized textures hold (those under the first frame's fit: `followed`), how far they bend in the
      // stabilized textures. (Measured at the points where the template belongs instead, 4.2 mm from those, the
      // texels picked for bending most there bent less at the points the textures hold: 0.75 of it in frames 0-12.)
      double bent_truth = 0, bent_stabilized = 0, bent_fused = 0;
      int64_t bent = 0;
      for (size_t i = 0; i < still.size(); ++i) {
        if (followed[0].state[i] != TexelState::kCovered || followed[k].state[i] != TexelState::kCovered ||
            s.textures.state[i] != TexelState::kCovered || fitted[0].state[i] != TexelState::kCovered ||
            fitted[k].state[i] != TexelState::kCovered) {
          continue;
        }
        auto angle = [&](const FusedTextures& a, const FusedTextures& b) {
          const float *p = &a.normal_object.pixels[3 * i], *q = &b.normal_object.pixels[3 * i];
          return AngleDeg(Eigen::Vector3d(p[0], p[1], p[2]), Eigen::Vector3d(q[0], q[1], q[2]));
        };
        const double t_angle = angle(followed[0], followed[k]);
        if (t_angle < 2) continue;
        bent_truth += t_angle;
        bent_stabilized += angle(fitted[0], s.textures);
        bent_fused += angle(fitted[0], fitted[k]);
        ++bent;
      }
      const double n_bent = static_cast<double>(std::max<int64_t>(1, bent));
      std::printf(
          "  wrinkles: %lld texels bent over 2 deg since frame 0, by %.2f deg on average; stabilized %.2f deg (%.2f of "
          "it), as fused %.2f\n",
          static_cast<long long>(bent), bent_truth / n_bent, bent_stabilized / n_bent,
          bent_stabilized / std::max(1e-9, bent_truth), bent_fused / n_bent);
      // Kept, not flattened: the goal is within 10 % (measured 2026-12-03, flow: 0.92, 1.06 and 0.99 of the truth's
      // bend; U-Net: 0.91, 1.01 and 0.98).
      EXPECT_GT(bent, 1000);
      EXPECT_GT(bent_stabilized, 0.85 * bent_truth) << frames[k];
      EXPECT_LT(bent_stabilized, 1.15 * bent_truth) << frames[k];
    }
    std::printf("mean jitter: %.2f %% as fused, %.2f %% stabilized (%.1fx less), %.2f %% without sliding\n",
                100 * raw / 3, 100 * stabilized / 3, raw / std::max(1e-9, stabilized), 100 * truth / 3);
    // Measured (2026-12-03): 3.19 % as fused; flow 0.87 % (3.7x less); U-Net 0.93 % (3.4x); 0.62 % with no sliding.
    EXPECT_LT(stabilized * 3, raw) << StabilizeMethodName(method);
  }
}

}  // namespace
}  // namespace stage::processing
