// Texture fusion on a closed-form scene: a cylindrical sheet (its UV layout its angle and height) seen by three
// cameras whose "photometric maps" are traced from the sheet itself, so the fused textures have an exact answer.
#include "stage/processing/texture_fusion.h"

#include <cmath>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/uv_raster.h"
#include "test_cameras.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

constexpr float kRadius = 100, kHalfAngle = 1.0f, kHalfHeight = 50;

// The sheet x = R sin(a), z = R cos(a), y in [-50, 50], a in [-1, 1] rad; u along a, v along y. Part 0.
TriangleMesh Sheet(int n = 40) {
  TriangleMesh m;
  for (int j = 0; j <= n; ++j) {
    for (int i = 0; i <= n; ++i) {
      const float u = static_cast<float>(i) / n, v = static_cast<float>(j) / n;
      const float a = (2 * u - 1) * kHalfAngle, y = (2 * v - 1) * kHalfHeight;
      m.positions.emplace_back(kRadius * std::sin(a), y, kRadius * std::cos(a));
      m.uvs.emplace_back(u, v);
    }
  }
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const int a = j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
      // Counter-clockwise seen from outside (+z side).
      m.triangles.push_back({a, b, d});
      m.triangles.push_back({a, d, c});
    }
  }
  m.parts.assign(m.triangles.size(), 0);
  return m;
}

// A plate of part 1 hovering in front of the sheet's right side (seen by the right camera only in front of it).
void AddOccluder(TriangleMesh* m) {
  const auto base = static_cast<int32_t>(m->positions.size());
  for (const auto& [x, y] : {std::pair{40.0f, -15.0f}, {70.0f, -15.0f}, {70.0f, 15.0f}, {40.0f, 15.0f}}) {
    m->positions.emplace_back(x + 40, y, 160);
    m->uvs.emplace_back(0, 0);
  }
  m->triangles.push_back({base, base + 1, base + 2});
  m->triangles.push_back({base, base + 2, base + 3});
  m->parts.insert(m->parts.end(), 2, 1);
}

float Pattern(const Eigen::Vector2f& uv) { return 0.5f + 0.3f * std::sin(6.0f * uv.x()) * std::cos(4.0f * uv.y()); }

CameraModel LookingAt(const Eigen::Vector3d& position, const Eigen::Vector3d& target = Eigen::Vector3d::Zero()) {
  return CameraLookingAt(position, target, 320, 240, 420);
}

// The maps a perfect photometric solve would give: per pixel, the albedo pattern (0.1 on the occluder) and a normal
// tilted `tilt` towards +u from the sheet's interpolated normal.
FusionView Trace(const std::string& id, const CameraModel& camera, const MeshBvh& scene, float tilt) {
  FusionView v;
  v.camera_id = id;
  v.camera = camera;
  const int w = camera.width(), h = camera.height();
  v.albedo = Image(w, h, 3);
  v.diffuse_normal = Image(w, h, 3);
  v.confidence = Image(w, h, 1);
  const TriangleMesh& m = scene.mesh();
  const std::vector<Eigen::Vector3f> normals = m.VertexNormals();
  const std::vector<Eigen::Vector4f> tangents = VertexTangents(m, normals);
  const std::vector<Eigen::Vector3f> rays = camera.PixelRays();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      MeshHit hit;
      if (!scene.Nearest(camera.position().cast<float>(), rays[static_cast<size_t>(y) * w + x], 1e4f, &hit)) continue;
      const auto& tri = m.triangles[static_cast<size_t>(hit.triangle)];
      const float b[3] = {1 - hit.b1 - hit.b2, hit.b1, hit.b2};
      Eigen::Vector2f uv = Eigen::Vector2f::Zero();
      Eigen::Vector3f n = Eigen::Vector3f::Zero(), t = Eigen::Vector3f::Zero();
      for (int k = 0; k < 3; ++k) {
        uv += b[k] * m.uvs[tri[k]];
        n += b[k] * normals[tri[k]];
        t += b[k] * tangents[tri[k]].head<3>();
      }
      n.normalize();
      t = (t - n * n.dot(t)).normalized();
      const bool occluder = m.parts[static_cast<size_t>(hit.triangle)] == 1;
      const float a = occluder ? 0.1f : Pattern(uv);
      const Eigen::Vector3f tilted = (n + tilt * t).normalized();
      for (int c = 0; c < 3; ++c) {
        v.albedo.at(x, y)[c] = a * (1.0f - 0.1f * c);
        v.diffuse_normal.at(x, y)[c] = tilted[c];
      }
      v.confidence.at(x, y)[0] = 1;
    }
  }
  return v;
}

struct Scene {
  TriangleMesh mesh = Sheet();
  std::vector<FusionView> views;
};

Scene MakeScene(bool occluder, float tilt = 0) {
  Scene s;
  TriangleMesh world = s.mesh;
  if (occluder) {
    AddOccluder(&world);
    s.mesh = world;
  }
  const MeshBvh bvh(world);
  for (const auto& [id, azimuth] : {std::pair{"left", -0.6}, {"centre", 0.0}, {"right", 0.6}}) {
    s.views.push_back(Trace(id, LookingAt({500 * std::sin(azimuth), 0, 500 * std::cos(azimuth)}), bvh, tilt));
  }
  return s;
}

FusionOptions Small() {
  FusionOptions o;
  o.size = 128;
  o.feather_px = 4;
  return o;
}

TEST(TextureFusionTest, TangentsFollowUAndTheBitangentsSignFollowsV) {
  TriangleMesh m = Sheet(4);
  std::vector<Eigen::Vector4f> t = VertexTangents(m, m.VertexNormals());
  // At the sheet's middle (a = 0) increasing u runs along +x and increasing v along +y = normal (+z) x tangent.
  const size_t middle = 2 * 5 + 2;
  EXPECT_NEAR(t[middle].x(), 1, 1e-5);
  EXPECT_EQ(t[middle].w(), 1);
  for (auto& uv : m.uvs) uv.x() = 1 - uv.x();  // mirrored along u
  t = VertexTangents(m, m.VertexNormals());
  EXPECT_NEAR(t[middle].x(), -1, 1e-5);
  EXPECT_EQ(t[middle].w(), -1);  // normal x tangent now points down v
}

TEST(TextureFusionTest, TheDepthBufferIsTheTracedDepth) {
  const Scene s = MakeScene(/*occluder=*/true);
  const MeshBvh bvh(s.mesh);
  const CameraModel& camera = s.views[2].camera;
  const std::vector<float> depth = DepthBuffer(s.mesh, camera);
  const std::vector<Eigen::Vector3f> rays = camera.PixelRays();
  int compared = 0, disagree = 0;
  double worst = 0;
  for (size_t i = 0; i < rays.size(); ++i) {
    MeshHit hit;
    const bool traced = bvh.Nearest(camera.position().cast<float>(), rays[i], 1e4f, &hit);
    if (traced != !std::isinf(depth[i])) ++disagree;  // a pixel centre on an outline may go either way
    if (!traced || std::isinf(depth[i])) continue;
    const double z = hit.t * rays[i].cast<double>().dot(camera.optical_axis());
    worst = std::max(worst, std::abs(z - depth[i]));
    ++compared;
  }
  EXPECT_GT(compared, 10000);  // of the 320 x 240 pixels
  EXPECT_LT(disagree, 20);
  EXPECT_LT(worst, 0.01);  // mm: perspective-correct across every triangle
}

TEST(TextureFusionTest, TheFusedAlbedoIsThePatternAndHiddenViewsDoNotCount) {
  const Scene s = MakeScene(/*occluder=*/true);
  auto fused = FuseTextures(s.mesh, Eigen::Isometry3f::Identity(), s.views, Small());
  ASSERT_TRUE(fused.ok()) << fused.status();
  ASSERT_EQ(fused->texels_per_view.size(), 3u);
  for (int64_t n : fused->texels_per_view) EXPECT_GT(n, 2000);
  int covered = 0;
  double worst = 0, sum = 0;
  for (int y = 0; y < 128; ++y) {
    for (int x = 0; x < 128; ++x) {
      const size_t t = static_cast<size_t>(y) * 128 + x;
      if (fused->state[t] != TexelState::kCovered) continue;
      ++covered;
      const float truth = Pattern(TexelUv(x, y, 128));
      for (int c = 0; c < 3; ++c) {
        const double e = std::abs(fused->albedo.at(x, y)[c] - truth * (1.0f - 0.1f * c));
        worst = std::max(worst, e);
        sum += e;
      }
    }
  }
  EXPECT_GT(covered, 128 * 128 * 8 / 10);
  // The occluder (albedo 0.1) in front of the right camera would pull texels behind it far down: none is off by more
  // than bilinear resampling gives.
  EXPECT_LT(worst, 0.01);
  EXPECT_LT(sum / (3 * covered), 0.002);
  // Dilation fills every texel of the square (the whole layout is covered, but for its border).
  int64_t empty = 0;
  for (TexelState st : fused->state) empty += st == TexelState::kEmpty;
  EXPECT_EQ(empty, 0);
}

TEST(TextureFusionTest, NormalsComeInTheHeadsFrameAndInTangentSpace) {
  const float tilt = 0.3f;
  const Scene s = MakeScene(/*occluder=*/false, tilt);
  const Eigen::Isometry3f head_from_stage(Eigen::AngleAxisf(0.4f, Eigen::Vector3f(1, 2, 3).normalized()));
  auto fused = FuseTextures(s.mesh, head_from_stage, s.views, Small());
  ASSERT_TRUE(fused.ok()) << fused.status();
  const Eigen::Vector3f expected = Eigen::Vector3f(tilt, 0, 1).normalized();
  double worst_tangent = 0, worst_object = 0;
  const std::vector<Eigen::Vector3f> vertex_normals = s.mesh.VertexNormals();
  for (int y = 4; y < 124; ++y) {
    for (int x = 4; x < 124; ++x) {
      if (fused->state[static_cast<size_t>(y) * 128 + x] != TexelState::kCovered) continue;
      const float* ts = fused->normal_tangent.at(x, y);
      const float cos_tangent = Eigen::Vector3f(ts[0], ts[1], ts[2]).dot(expected);
      worst_tangent = std::max(worst_tangent, static_cast<double>(std::acos(std::min(1.0f, cos_tangent))));
      // The object-space normal taken back to the stage: the sheet's normal tilted towards +u (the azimuth).
      const float* os = fused->normal_object.at(x, y);
      const Eigen::Vector3f stage = head_from_stage.linear().transpose() * Eigen::Vector3f(os[0], os[1], os[2]);
      const float a = (2 * TexelUv(x, y, 128).x() - 1) * kHalfAngle;
      const Eigen::Vector3f normal(std::sin(a), 0, std::cos(a)), along_u(std::cos(a), 0, -std::sin(a));
      const float cos_object = stage.dot((normal + tilt * along_u).normalized());
      worst_object = std::max(worst_object, static_cast<double>(std::acos(std::min(1.0f, cos_object))));
    }
  }
  EXPECT_LT(worst_tangent * 180 / M_PI, 0.3);
  EXPECT_LT(worst_object * 180 / M_PI, 0.6);  // the facets' interpolated normals against the true cylinder's
}

// A mesh wound the other way (normals into the surface) fuses the same textures: the views say which side is out.
TEST(TextureFusionTest, AMeshWoundInsideOutFusesTheSame) {
  const Scene s = MakeScene(/*occluder=*/false, 0.3f);
  TriangleMesh flipped = s.mesh;
  for (auto& tri : flipped.triangles) std::swap(tri[1], tri[2]);
  auto fused = FuseTextures(s.mesh, Eigen::Isometry3f::Identity(), s.views, Small());
  auto inside_out = FuseTextures(flipped, Eigen::Isometry3f::Identity(), s.views, Small());
  ASSERT_TRUE(fused.ok() && inside_out.ok());
  EXPECT_EQ(fused->state, inside_out->state);
  double worst = 0;
  for (size_t i = 0; i < fused->albedo.pixels.size(); ++i) {
    worst = std::max(worst, static_cast<double>(std::abs(fused->albedo.pixels[i] - inside_out->albedo.pixels[i])));
  }
  for (size_t i = 0; i < fused->normal_tangent.pixels.size(); ++i) {
    worst = std::max(
        worst, static_cast<double>(std::abs(fused->normal_tangent.pixels[i] - inside_out->normal_tangent.pixels[i])));
  }
  EXPECT_LT(worst, 1e-5);
}

TEST(TextureFusionTest, RefusesBadOptionsAMeshWithoutUvsAndMapsOfTheWrongSize) {
  Scene s = MakeScene(/*occluder=*/false);
  FusionOptions o = Small();
  o.max_view_angle_deg = 90;
  EXPECT_THAT(std::string(FuseTextures(s.mesh, {}, s.views, o).status().message()), HasSubstr("max_view_angle_deg"));
  TriangleMesh bare = s.mesh;
  bare.uvs.clear();
  EXPECT_THAT(std::string(FuseTextures(bare, {}, s.views, Small()).status().message()),
              HasSubstr("texture coordinate"));
  s.views[1].albedo = Image(10, 10, 3);
  EXPECT_THAT(std::string(FuseTextures(s.mesh, Eigen::Isometry3f::Identity(), s.views, Small()).status().message()),
              HasSubstr("view centre: the albedo map is 10 x 10 x 3, not 320 x 240 x 3"));
}

// Lobes measured on the sheet's left half only (u < 0.5 seen by each view: specular 0.04, roughness 0.3, the
// specular normal the diffuse one tilted), one speck of a bad fit among them (specular 1.0): the fused lobe maps hold
// the measured values on the left, the typical ones on the right with the diffuse normal as the specular one, and
// the speck is rejected like an unmeasured texel.
TEST(TextureFusionTest, LobesComeFromWhereTheyWereMeasuredAndOutliersAreFilled) {
  Scene s = MakeScene(/*occluder=*/false);
  for (FusionView& v : s.views) {
    const int w = v.camera.width(), h = v.camera.height();
    v.specular = Image(w, h, 1);
    v.roughness = Image(w, h, 1);
    v.specular_normal = Image(w, h, 3);
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const float* n = v.diffuse_normal.at(x, y);
        // The sheet's left half (x < 0 in the stage frame) faces cameras whose image x grows with stage x.
        if (n[0] == 0 && n[1] == 0 && n[2] == 0) continue;
        const Eigen::Vector3f normal(n[0], n[1], n[2]);
        if (std::atan2(normal.x(), normal.z()) > 0) continue;  // the sheet's angle a = atan2(x, z) > 0: u > 0.5
        const bool speck = x == w / 2 - 30 && y == h / 2;
        v.specular.at(x, y)[0] = speck ? 1.0f : 0.04f;
        v.roughness.at(x, y)[0] = 0.3f;
        const Eigen::Vector3f tilted = (normal + Eigen::Vector3f(0, 0.05f, 0)).normalized();
        for (int c = 0; c < 3; ++c) v.specular_normal.at(x, y)[c] = tilted[c];
      }
    }
  }
  auto fused = FuseTextures(s.mesh, Eigen::Isometry3f::Identity(), s.views, Small());
  ASSERT_TRUE(fused.ok()) << fused.status();
  const int size = Small().size;
  int left = 0, right = 0, halo = 0;
  for (int y = size / 4; y < 3 * size / 4; ++y) {
    for (int x = 4; x < size - 4; ++x) {
      const size_t t = static_cast<size_t>(y) * size + x;
      if (fused->state[t] != TexelState::kCovered) continue;
      const float u = TexelUv(x, y, size).x();
      const float* sn = &fused->specular_normal_object.pixels[3 * t];
      const float* dn = &fused->normal_object.pixels[3 * t];
      const double apart = AngleDeg(Eigen::Vector3d(sn[0], sn[1], sn[2]), Eigen::Vector3d(dn[0], dn[1], dn[2]));
      if (u < 0.45f && fused->specular_weight.pixels[t] > 0) {
        ++left;
        // Beside the speck its value blends in (up to 4x the typical one before it is rejected).
        if (std::abs(fused->specular.pixels[t] - 0.04f) > 1e-4) ++halo;
        EXPECT_NEAR(fused->roughness.pixels[t], 0.3f, 1e-4);
        EXPECT_GT(apart, 2.0);  // the tilted lobe's own normal
      } else if (u > 0.55f) {
        ++right;
        EXPECT_EQ(fused->specular_weight.pixels[t], 0);
        EXPECT_NEAR(fused->specular.pixels[t], 0.04f, 1e-3) << x << "," << y;  // the typical value, filled
        EXPECT_NEAR(fused->roughness.pixels[t], 0.3f, 1e-3);
        EXPECT_LT(apart, 1e-3);  // the diffuse normal
      }
    }
  }
  EXPECT_GT(left, 1000);
  EXPECT_GT(right, 1000);
  EXPECT_LT(halo, 30);
  EXPECT_GT(fused->lobes_rejected, 0);  // the speck's texels
  EXPECT_LT(fused->lobes_rejected, 40);
}

// A view's lobe counts only where the view sees the surface within max_lobe_view_angle_deg of its normal: one camera
// in front of the sheet, lobes measured everywhere it looks, the lobe angle 20 deg; the diffuse maps go to 75 deg.
TEST(TextureFusionTest, ALobeSeenTooObliquelyIsNotFused) {
  Scene s = MakeScene(/*occluder=*/false);
  FusionView v = s.views[1];  // the centre camera, on the sheet's axis at 500 mm
  ASSERT_EQ(v.camera_id, "centre");
  const int w = v.camera.width(), h = v.camera.height();
  v.specular = Image(w, h, 1);
  v.roughness = Image(w, h, 1);
  v.specular_normal = v.diffuse_normal;
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      v.specular.at(x, y)[0] = 0.04f;
      v.roughness.at(x, y)[0] = 0.3f;
    }
  }
  FusionOptions o = Small();
  o.max_lobe_view_angle_deg = 20;
  auto fused = FuseTextures(s.mesh, Eigen::Isometry3f::Identity(), {v}, o);
  ASSERT_TRUE(fused.ok()) << fused.status();
  int within = 0, beyond = 0;
  for (int y = 0; y < o.size; ++y) {
    for (int x = 0; x < o.size; ++x) {
      const size_t t = static_cast<size_t>(y) * o.size + x;
      if (fused->state[t] != TexelState::kCovered) continue;
      // The texel's point on the sheet and the angle at which the camera sees it.
      const Eigen::Vector2f uv = TexelUv(x, y, o.size);
      const float a = (2 * uv.x() - 1) * kHalfAngle, height = (2 * uv.y() - 1) * kHalfHeight;
      const Eigen::Vector3f point(kRadius * std::sin(a), height, kRadius * std::cos(a)),
          normal(std::sin(a), 0, std::cos(a));
      const double angle = AngleDeg(normal.cast<double>(), (v.camera.position().cast<float>() - point).cast<double>());
      if (angle < 18) {
        ++within;
        EXPECT_GT(fused->specular_weight.pixels[t], 0) << x << "," << y << ": seen at " << angle << " deg";
      } else if (angle > 22) {
        ++beyond;
        EXPECT_EQ(fused->specular_weight.pixels[t], 0) << x << "," << y << ": seen at " << angle << " deg";
        EXPECT_GT(fused->weight.pixels[t], 0);  // its diffuse maps are fused
      }
    }
  }
  EXPECT_GT(within, 500);
  EXPECT_GT(beyond, 500);
  o.max_lobe_view_angle_deg = 0;
  EXPECT_THAT(std::string(FuseTextures(s.mesh, {}, {v}, o).status().message()), HasSubstr("max_lobe_view_angle_deg"));
}

// Lobes measured only at scattered pixels (every 9th column of every 9th row): no cell of the layout is a quarter
// measured, and the lobes measured still say what the rest is; none is taken for an outlier.
TEST(TextureFusionTest, ScatteredLobesStillFillTheRest) {
  Scene s = MakeScene(/*occluder=*/false);
  for (FusionView& v : s.views) {
    const int w = v.camera.width(), h = v.camera.height();
    v.specular = Image(w, h, 1);
    v.roughness = Image(w, h, 1);
    v.specular_normal = Image(w, h, 3);
    for (int y = 0; y < h; y += 9) {
      for (int x = 0; x < w; x += 9) {
        const float* n = v.diffuse_normal.at(x, y);
        if (n[0] == 0 && n[1] == 0 && n[2] == 0) continue;
        v.specular.at(x, y)[0] = 0.04f;
        v.roughness.at(x, y)[0] = 0.3f;
        std::copy_n(n, 3, v.specular_normal.at(x, y));
      }
    }
  }
  auto fused = FuseTextures(s.mesh, Eigen::Isometry3f::Identity(), s.views, Small());
  ASSERT_TRUE(fused.ok()) << fused.status();
  EXPECT_EQ(fused->lobes_rejected, 0);
  int covered = 0;
  for (size_t t = 0; t < fused->state.size(); ++t) {
    if (fused->state[t] != TexelState::kCovered) continue;
    ++covered;
    ASSERT_NEAR(fused->specular.pixels[t], 0.04f, 1e-4) << t;
    ASSERT_NEAR(fused->roughness.pixels[t], 0.3f, 1e-4) << t;
  }
  EXPECT_GT(covered, 5000);
}

TEST(TextureFusionTest, AJobNamesItsTakeFramesAndCameras) {
  TexturesJob job;
  EXPECT_THAT(std::string(job.Validate().message()), HasSubstr("no take directory"));
  job.take_dir = "/nonexistent-take";
  EXPECT_TRUE(job.Validate().ok());
  job.first_frame = 4;
  job.last_frame = 4;
  EXPECT_THAT(std::string(job.Validate().message()), HasSubstr("[4, 4) hold none"));
  job.last_frame = -1;
  job.cameras = {"hs-1", ""};
  EXPECT_THAT(std::string(job.Validate().message()), HasSubstr("empty camera id"));
  job.cameras = {"hs-1"};
  job.options.size = 8;
  EXPECT_THAT(std::string(RunTextures(job).status().message()), HasSubstr("size"));
}

}  // namespace
}  // namespace stage::processing
