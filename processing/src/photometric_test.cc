// Photometric stereo on an analytic sphere: images made from the light model in closed form (a Lambertian sphere,
// with or without a GGX specular lobe, under the shipped rig's 168 units and 38 patterns, seen from +z), with and
// without the sensor's noise (full-on 4000 e- for white, read noise 5 e-, 12-bit). The solver must return the
// sphere's normals, albedo, specular intensity and roughness; a mislabeled pattern must raise the error and be
// flagged.
#include "stage/processing/photometric.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "shipped_light.h"
#include "stage/common/rig.h"
#include "stage/processing/visual_hull.h"
#include "test_sphere.h"

namespace stage::processing {
namespace {

// The plane z = 0 for x < 0 only: a mesh that ends where the surface goes on (a reconstruction's edge).
TriangleMesh HalfPlane() {
  TriangleMesh m;
  m.positions = {{-50, -50, 0}, {0, -50, 0}, {0, 50, 0}, {-50, 50, 0}};
  m.triangles = {{0, 1, 2}, {0, 2, 3}};
  return m;
}

// `h` rows of `w` pixels 1 mm apart on z = 0, centred on the origin (x = -(w - 1) / 2 ..), seen from 1 m above.
PhotometricCamera RowsFromAbove(int w, int h = 1) {
  PhotometricCamera camera;
  camera.position_mm = {0, 0, 1000};
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      camera.rays.push_back(
          (Eigen::Vector3d(x - (w - 1) / 2.0, y - (h - 1) / 2.0, 0) - camera.position_mm).normalized().cast<float>());
    }
  }
  return camera;
}

// Every pattern's `w` x `h` image, 1000 DN in every channel.
std::vector<Image> EvenFrames(const LightModel& light, int w, int h = 1) {
  std::vector<Image> frames(light.patterns.size(), Image(w, h, 3));
  for (Image& f : frames) std::fill(f.pixels.begin(), f.pixels.end(), 1000.f);
  return frames;
}

// Up to 70 degrees of tilt the solver returns the sphere: diffuse and specular, where the lobe meets the dome.
TEST(PhotometricTest, ExactImagesGiveTheSpheresMaps) {
  const LightModel light = ShippedLight();
  ASSERT_EQ(light.patterns.size(), 38u);
  const Sphere s = MakeSphere(light, 96, /*noisy=*/false, /*specular=*/0.03);
  auto m = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(m.ok()) << m.status();
  const Errors e = Measure(light, s, *m, 70);
  Print("sphere with a lobe, exact", e);
  EXPECT_GT(e.pixels, 5000);
  // Only the table's interpolation separates the diffuse from the truth.
  EXPECT_LT(e.mean_deg, 0.1);
  EXPECT_LT(e.max_deg, 1.0);
  EXPECT_LT(e.albedo_rel, 0.002);
  // The lobe is measured on most pixels whose mirror direction meets the dome (the rest: lobes half off its edge,
  // whose predicted noise is too high to count), and is exact there.
  EXPECT_GT(e.mirrored_with_lobe, e.mirrored * 7 / 10);
  EXPECT_LT(e.specular_deg, 0.2);
  EXPECT_LT(e.specular_rel, 0.01);
  EXPECT_LT(e.roughness_abs, 0.005);
  // The camera frame: the sphere's centre faces the camera (z towards it is -z in the camera frame).
  const float* centre = m->diffuse_normal_camera.at(48, 48);
  EXPECT_LT(centre[2], -0.99);
}

// Full-on 4000 e- for white, read noise 5 e-, 12-bit. Goals (issue #6): diffuse normals <= 1.5 deg mean, albedo
// <= 0.7 %, on a Lambertian sphere (albedo 0.6, 0.45, 0.35).
TEST(PhotometricTest, NoisyImagesMeetTheDiffuseGoalsOnALambertianSphere) {
  const LightModel light = ShippedLight();
  const Sphere s = MakeSphere(light, 96, /*noisy=*/true, /*specular=*/0);
  auto m = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(m.ok()) << m.status();
  const Errors e = Measure(light, s, *m, 70);
  Print("Lambertian sphere, noisy", e);
  EXPECT_LT(e.mean_deg, 1.5);
  EXPECT_LT(e.albedo_rel, 0.007);
}

// The same sphere with a lobe (rho_s 0.03, roughness 0.3). Goals: specular normals <= 5 deg, roughness <= 0.05 mean
// absolute error. The lobe's own noise reaches the diffuse that is left when it is taken away: the albedo is at
// 0.78 % here (issue #6 asks 0.7 %).
TEST(PhotometricTest, NoisyImagesMeetTheSpecularGoalsOnASphereWithALobe) {
  const LightModel light = ShippedLight();
  const Sphere s = MakeSphere(light, 96, /*noisy=*/true, /*specular=*/0.03);
  auto m = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(m.ok()) << m.status();
  const Errors e = Measure(light, s, *m, 70);
  Print("sphere with a lobe, noisy", e);
  EXPECT_LT(e.mean_deg, 1.5);
  EXPECT_LT(e.albedo_rel, 0.008);
  EXPECT_GT(e.mirrored_with_lobe, e.mirrored / 2);
  EXPECT_LT(e.specular_deg, 5);
  EXPECT_LT(e.roughness_abs, 0.05);
}

// x+ and x- swapped (a sequencing error): the normals turn wrong and the fit says so.
TEST(PhotometricTest, AMislabeledPatternRaisesTheErrorAndIsFlagged) {
  const LightModel light = ShippedLight();
  Sphere s = MakeSphere(light, 64, /*noisy=*/true, /*specular=*/0.03);
  auto good = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(good.ok());
  const int xp = *light.Find("cross-x+"), xm = *light.Find("cross-x-");
  std::swap(s.frames[static_cast<size_t>(xp)], s.frames[static_cast<size_t>(xm)]);
  auto bad = SolvePhotometric(light, s.frames, s.camera);
  ASSERT_TRUE(bad.ok());
  const Errors eg = Measure(light, s, *good, 70), eb = Measure(light, s, *bad, 70);
  Print("mislabeled", eb);
  EXPECT_GT(eb.mean_deg, 5 * eg.mean_deg);
  int flagged_good = 0, flagged_bad = 0;
  double conf_good = 0, conf_bad = 0;
  for (size_t i = 0; i < good->flags.size(); ++i) {
    if (s.normals[i].isZero()) continue;
    flagged_good += (good->flags[i] & kBadFit) != 0;
    flagged_bad += (bad->flags[i] & kBadFit) != 0;
    conf_good += good->confidence.pixels[i];
    conf_bad += bad->confidence.pixels[i];
  }
  EXPECT_GT(flagged_bad, 10 * std::max(1, flagged_good));
  EXPECT_LT(conf_bad, 0.5 * conf_good);
}

TEST(PhotometricTest, BadInputIsNamed) {
  const LightModel light = ShippedLight();
  std::vector<Image> frames(light.patterns.size(), Image(8, 8, 3));
  frames[5] = Image(8, 4, 3);
  auto m = SolvePhotometric(light, frames, PhotometricCamera());
  ASSERT_FALSE(m.ok());
  EXPECT_THAT(m.status().message(), ::testing::HasSubstr(light.patterns[5].name));
  frames.pop_back();
  EXPECT_FALSE(SolvePhotometric(light, frames, PhotometricCamera()).ok());
}

// A reconstructed surface is rough at the scale of its error; its own facets must not shadow it, while a real occluder
// must. A plane with bumps of +-0.3 mm every 0.5 mm, and a plate 20 mm above part of it.
TEST(PhotometricTest, ShadowRaysClearTheGeometrysOwnRoughnessButNotARealOccluder) {
  const LightModel light = ShippedLight();
  TriangleMesh m;
  const int n = 121;  // 60 mm a side
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const uint32_t h = (static_cast<uint32_t>(i) * 73856093u) ^ (static_cast<uint32_t>(j) * 19349663u);
      const float bump = 0.3f * (static_cast<float>(h % 1000) / 500.f - 1.f);
      m.positions.emplace_back(0.5f * (i - 60), 0.5f * (j - 60), bump);
    }
  }
  for (int j = 0; j + 1 < n; ++j) {
    for (int i = 0; i + 1 < n; ++i) {
      const int a = j * n + i;
      m.triangles.push_back({a, a + 1, a + n + 1});
      m.triangles.push_back({a, a + n + 1, a + n});
    }
  }
  const int32_t p = static_cast<int32_t>(m.positions.size());
  for (const auto& [x, y] : std::vector<std::pair<float, float>>{{5, -10}, {25, -10}, {25, 10}, {5, 10}}) {
    m.positions.emplace_back(x, y, 20);
  }
  m.triangles.push_back({p, p + 1, p + 2});
  m.triangles.push_back({p, p + 2, p + 3});
  const MeshBvh bvh(m);
  // Nine pixels looking down at points about the origin.
  PhotometricCamera camera;
  camera.position_mm = {0, 0, 1000};
  for (int k = 0; k < 9; ++k) {
    const Eigen::Vector3d at(0.7 * (k % 3 - 1), 0.7 * (k / 3 - 1), 0);
    camera.rays.push_back((at - camera.position_mm).normalized().cast<float>());
  }
  auto hidden = [&](double clearance_mm, int64_t* by_plate, int64_t* above_20_deg) {
    const PixelGeometry g = TraceGeometry(bvh, camera, 9, 1, light, clearance_mm, 1);
    *by_plate = *above_20_deg = 0;
    for (size_t i = 0; i < 9; ++i) {
      EXPECT_TRUE(g.Covers(i));
      const Eigen::Vector3d x(g.points[3 * i], g.points[3 * i + 1], g.points[3 * i + 2]);
      for (int l = 0; l < light.units(); ++l) {
        const Eigen::Vector3d d = (light.directions[l] * light.radius_mm - x).normalized();
        const bool seen = (g.Visible(i)[l / 64] >> (l % 64)) & 1u;
        // Through the plate (with a margin for the point's place): must be hidden.
        const Eigen::Vector2d at = x.head<2>() + (20 - x.z()) / d.z() * d.head<2>();
        if (d.z() > 0 && at.x() > 6 && at.x() < 24 && std::abs(at.y()) < 9) {
          if (!seen) ++*by_plate;
          EXPECT_FALSE(seen) << "unit " << l << " is behind the plate";
        } else if (d.z() > std::sin(20 * M_PI / 180) && !seen && (at.x() < 4 || at.x() > 26 || std::abs(at.y()) > 11)) {
          ++*above_20_deg;
        }
      }
    }
  };
  int64_t plate = 0, rough = 0;
  hidden(2, &plate, &rough);
  EXPECT_GT(plate, 0) << "no unit lies behind the plate: the test sees nothing";
  EXPECT_EQ(rough, 0) << "units above 20 degrees hidden by the surface's own bumps";
  // Without the clearance, the bumps hide some of them. (Units whose ray passes within a millimetre of the plate's
  // edge are counted neither way.)
  hidden(0, &plate, &rough);
  EXPECT_GT(rough, 0);
  PhotometricOptions bad;
  bad.shadow_clearance_mm = -1;
  EXPECT_THAT(std::string(bad.Validate().message()), ::testing::HasSubstr("shadow_clearance_mm"));
}

// PhotometricSolver::SolveAgain after the geometry of some pixels changed (the refill moves the placed ones): only
// those are fitted again, and the maps are those a full solve at the new geometry gives, bit for bit, with a Bayer
// mosaic (the albedo demosaiced across neighbours) and without, on two threads.
TEST(PhotometricTest, SolvingAgainWhereTheGeometryChangedGivesTheFullSolvesMaps) {
  const LightModel light = ShippedLight();
  const int size = 40;
  Sphere s = MakeSphere(light, size, /*noisy=*/true, /*specular=*/0.03);
  // The sphere 60 mm across at the origin, every unit in sight; the pixels right of centre then move 8 mm towards the
  // camera and lose the units below the horizon of +x.
  const double radius = 30;
  PixelGeometry before;
  before.width = before.height = size;
  before.words = (light.units() + 63) / 64;
  before.points.assign(3 * static_cast<size_t>(size) * size, std::nanf(""));
  before.visible.assign(static_cast<size_t>(size) * size * before.words, ~uint64_t{0});
  before.placed.assign(static_cast<size_t>(size) * size, 0);
  PixelGeometry after = before;
  int moved = 0;
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const size_t i = static_cast<size_t>(y) * size + x;
      const Eigen::Vector3d& n = s.normals[i];
      if (n.isZero()) continue;
      const Eigen::Vector3f point = (radius * n).cast<float>();
      std::copy_n(point.data(), 3, &before.points[3 * i]);
      std::copy_n(point.data(), 3, &after.points[3 * i]);
      if (x < size / 2 + 4) continue;
      after.placed[i] = 1;
      after.points[3 * i + 2] += 8;
      uint64_t* bits = &after.visible[i * static_cast<size_t>(after.words)];
      for (int l = 0; l < light.units(); ++l) {
        if (light.directions[static_cast<size_t>(l)].x() < -0.2) bits[l / 64] &= ~(uint64_t{1} << (l % 64));
      }
      ++moved;
    }
  }
  ASSERT_GT(moved, 200);
  for (const bool mosaic : {false, true}) {
    SCOPED_TRACE(mosaic ? "Bayer mosaic" : "RGB");
    s.camera.mosaic.reset();
    if (mosaic) s.camera.mosaic = Mosaic{};
    PhotometricOptions options;
    options.threads = 2;
    auto full = SolvePhotometric(light, s.frames, s.camera, options, &after);
    ASSERT_TRUE(full.ok()) << full.status();
    auto solver = PhotometricSolver::Create(light, s.frames, s.camera, options);
    ASSERT_TRUE(solver.ok()) << solver.status();
    EXPECT_EQ((*solver)->SolveAgain(after, after.placed).status().code(), absl::StatusCode::kFailedPrecondition);
    // Solved without keeping its fits (as SolvePhotometric does): it cannot be solved again either.
    ASSERT_TRUE((*solver)->Solve(&before, /*again=*/false).ok());
    EXPECT_EQ((*solver)->SolveAgain(after, after.placed).status().code(), absl::StatusCode::kFailedPrecondition);
    auto first = (*solver)->Solve(&before);
    ASSERT_TRUE(first.ok()) << first.status();
    EXPECT_EQ((*solver)->SolveAgain(after, {1, 0}).status().code(), absl::StatusCode::kInvalidArgument);
    auto again = (*solver)->SolveAgain(after, after.placed);
    ASSERT_TRUE(again.ok()) << again.status();
    int changed = 0;
    for (size_t i = 0; i < after.placed.size(); ++i) {
      changed += first->diffuse_normal_world.pixels[3 * i] != full->diffuse_normal_world.pixels[3 * i];
    }
    EXPECT_GT(changed, moved / 2) << "the new geometry hardly changes the maps: the test sees nothing";
    ExpectSameMaps(*again, *full);
  }
}

// A mesh that stops where the surface goes on (a reconstruction's edge at the side of the head): the pixels beyond
// it that are lit, and no further than geometry_fill_px, are placed near the surface; dark ones and far ones are not.
TEST(PhotometricTest, PixelsTheMeshMissesNearItsEdgeArePlacedAtTheirNeighboursDistance) {
  const LightModel light = ShippedLight();
  const MeshBvh bvh(HalfPlane());
  const int w = 20;  // a row of pixels 1 mm apart on the plane, x = -9.5 .. 9.5
  const PhotometricCamera camera = RowsFromAbove(w);
  PixelGeometry g = TraceGeometry(bvh, camera, w, 1, light, 2, 1);
  for (int x = 0; x < w; ++x) EXPECT_EQ(g.Covers(static_cast<size_t>(x)), x < 10) << x;
  // Every pattern's image bright but for the last pixel, dark.
  std::vector<Image> frames(light.patterns.size(), Image(w, 1, 3));
  for (Image& f : frames) {
    for (int x = 0; x + 1 < w; ++x) f.pixels[3 * x] = f.pixels[3 * x + 1] = f.pixels[3 * x + 2] = 1000;
  }
  PhotometricOptions options;
  options.threads = 1;
  options.geometry_fill_px = 4;
  auto filled = FillGeometry(bvh, camera, light, frames, options, &g);
  ASSERT_TRUE(filled.ok()) << filled.status();
  EXPECT_EQ(*filled, 4);
  for (int x = 10; x < w; ++x) {
    SCOPED_TRACE(x);
    EXPECT_EQ(g.Covers(static_cast<size_t>(x)), x < 14);
    if (x >= 14) continue;
    // At the edge's distance along its own ray: on the plane within the rays' spread (4 mm over 1 m).
    EXPECT_NEAR(g.points[3 * x + 2], 0, 0.05);
    EXPECT_NEAR(g.points[3 * x], x - 9.5, 0.01);
    // Units above the plane seen from there: most of the dome's upper half.
    int seen = 0;
    for (int l = 0; l < light.units(); ++l) seen += (g.Visible(static_cast<size_t>(x))[l / 64] >> (l % 64)) & 1u;
    EXPECT_GT(seen, light.units() / 3);
  }
  options.geometry_fill_px = 100;  // the dark pixel stays unplaced
  g = TraceGeometry(bvh, camera, w, 1, light, 2, 1);
  filled = FillGeometry(bvh, camera, light, frames, options, &g);
  ASSERT_TRUE(filled.ok());
  EXPECT_EQ(*filled, 9);
  EXPECT_FALSE(g.Covers(w - 1));
  options.geometry_fill_px = -1;
  EXPECT_THAT(std::string(options.Validate().message()), ::testing::HasSubstr("geometry_fill_px"));
}

// Past the mesh's edge a 45-degree slope goes down (the side of the head), or up (a cheek past a fold): a view from the
// side sees the subject's profile, so the visual hull is the solid under the surface. FillGeometry puts the pixels past
// the edge at the edge's distance: millimetres above the falling slope, or behind the rising one, inside the solid.
// Within the hull they land on the falling slope (its entry); behind the rising one they come to within
// geometry_hull_depth_mm (3 here) of the entry.
TEST(PhotometricTest, PlacedPixelsAreKeptInsideTheVisualHull) {
  const LightModel light = ShippedLight();
  const MeshBvh bvh(HalfPlane());
  const int w = 20;  // pixels 1 mm apart, x = -9.5 .. 9.5
  const PhotometricCamera camera = RowsFromAbove(w);
  const std::vector<Image> frames = EvenFrames(light, w);
  // The side view, 1 m along -y looking at the origin (image x along +x, image y down along -z), 0.2 mm a pixel over
  // +-110 mm: the whole stretch the rays are searched over (a view says nothing of what its image does not hold).
  CameraParameters side;
  side.width = side.height = 1100;
  side.fx = side.fy = 5000;
  side.cx = side.cy = 549.5;
  side.position = {0, -1000, 0};
  side.rotation << 1, 0, 0, 0, 0, -1, 0, 1, 0;
  auto model = CameraModel::FromParameters(side);
  ASSERT_TRUE(model.ok()) << model.status();
  PhotometricOptions options;
  options.threads = 1;
  options.geometry_fill_px = 10;
  options.geometry_hull_depth_mm = 3;
  for (const int rise : {-1, 1}) {  // the surface past the edge: z = rise * x
    SCOPED_TRACE(rise < 0 ? "falling" : "rising");
    Silhouette profile{"side", *model, std::vector<uint8_t>(1100 * 1100)};
    for (int v = 0; v < 1100; ++v) {
      for (int u = 0; u < 1100; ++u) {
        const double x = (u - side.cx) / side.fx * 1000, z = -(v - side.cy) / side.fy * 1000;
        profile.inside[static_cast<size_t>(v) * 1100 + u] = z <= (x < 0 ? 0 : rise * x);
      }
    }
    const VisualHull hull({profile});
    for (const bool with_hull : {false, true}) {
      SCOPED_TRACE(with_hull ? "with the hull" : "without");
      PixelGeometry g = TraceGeometry(bvh, camera, w, 1, light, 2, 1);
      auto filled = FillGeometry(bvh, camera, light, frames, options, &g, with_hull ? &hull : nullptr);
      ASSERT_TRUE(filled.ok()) << filled.status();
      ASSERT_EQ(*filled, 10);
      EXPECT_EQ(g.hull_in.empty(), !with_hull);
      for (int x = 11; x < w; ++x) {
        SCOPED_TRACE(x);
        // Where the pixel's ray, origin + s (a, 0, -1000), meets the slope, and the point's distance along it.
        const double a = x - 9.5, s = 1000 / (1000 + rise * a);
        const double slope_z = 1000 - 1000 * s, slope_distance = s * std::hypot(a, 1000.0);
        const double distance =
            (Eigen::Map<const Eigen::Vector3f>(&g.points[3 * x]) - Eigen::Vector3f(0, 0, 1000)).norm();
        if (!with_hull) {
          EXPECT_NEAR(g.points[3 * x + 2], 0, 0.05);
          continue;
        }
        // The hull's entry at the slope, within the side view's pixel (0.2 mm); its far end 3 mm on.
        EXPECT_NEAR(g.hull_in[static_cast<size_t>(x)], slope_distance, 0.2);
        EXPECT_NEAR(g.hull_out[static_cast<size_t>(x)], g.hull_in[static_cast<size_t>(x)] + 3, 0.2);
        if (rise < 0) {
          EXPECT_NEAR(g.points[3 * x + 2], slope_z, 0.2);
        } else {
          // Up to 9.5 mm behind without the hull (on the plane z = 0).
          EXPECT_LE(distance, slope_distance + 3.2);
          EXPECT_GE(distance, slope_distance - 0.2);
        }
      }
      if (!with_hull || rise < 0) continue;
      // Refilled along normals that say the plane goes on flat (as across a fold), the rings carry the plane's
      // distance out, behind the rising slope: the hull's bound holds each one.
      Image flat(w, 1, 3);
      for (int x = 0; x < w; ++x) flat.pixels[3 * x + 2] = 1;
      auto refilled = RefillGeometry(bvh, camera, light, flat, options, &g);
      ASSERT_TRUE(refilled.ok()) << refilled.status();
      ASSERT_EQ(*refilled, 10);
      for (int x = 14; x < w; ++x) {
        SCOPED_TRACE(x);
        const double a = x - 9.5, s = 1000 / (1000 + a);
        const double slope_distance = s * std::hypot(a, 1000.0);
        const double distance =
            (Eigen::Map<const Eigen::Vector3f>(&g.points[3 * x]) - Eigen::Vector3f(0, 0, 1000)).norm();
        EXPECT_LE(distance, slope_distance + 3.2);
        EXPECT_GE(distance, slope_distance + 2.8) << "the flat normals should have carried it behind the bound";
      }
    }
  }
  // Switched off, the hull is not used.
  options.geometry_hull = false;
  PixelGeometry g = TraceGeometry(bvh, camera, w, 1, light, 2, 1);
  const VisualHull hull({Silhouette{"side", *model, std::vector<uint8_t>(1100 * 1100, 1)}});
  ASSERT_TRUE(FillGeometry(bvh, camera, light, frames, options, &g, &hull).ok());
  EXPECT_TRUE(g.hull_in.empty());
  options.geometry_hull_depth_mm = 0;
  EXPECT_THAT(std::string(options.Validate().message()), ::testing::HasSubstr("geometry_hull_depth_mm"));
}

// Past the mesh's edge the surface turns away from the camera (a 45-degree slope, as the side of the head past a
// reconstruction's edge): FillGeometry places those pixels at the edge's distance, millimetres above the slope;
// RefillGeometry, given the surface's normals, places them on it, and traces their shadows from there.
TEST(PhotometricTest, PlacedPixelsAreRefilledAlongTheSurfaceTheNormalsDescribe) {
  const LightModel light = ShippedLight();
  const MeshBvh bvh(HalfPlane());  // beyond its edge the true surface is z = -x
  const int w = 20, h = 3;         // rows of 20 pixels 1 mm apart, x = -9.5 .. 9.5
  const PhotometricCamera camera = RowsFromAbove(w, h);
  const std::vector<Image> frames = EvenFrames(light, w, h);
  PhotometricOptions options;
  options.threads = 1;
  options.geometry_fill_px = 8;
  PixelGeometry g = TraceGeometry(bvh, camera, w, h, light, 2, 1);
  auto filled = FillGeometry(bvh, camera, light, frames, options, &g);
  ASSERT_TRUE(filled.ok()) << filled.status();
  ASSERT_EQ(*filled, 8 * h);
  // The surface's normals: up on the plane, tilted 45 degrees past its edge.
  Image normals(w, h, 3);
  const Eigen::Vector3f up(0, 0, 1), slope = Eigen::Vector3f(1, 0, 1).normalized();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) std::copy_n((x < 10 ? up : slope).data(), 3, normals.at(x, y));
  }
  // How far each placed point lies from the slope (along z), before and after.
  auto off_slope = [&](const PixelGeometry& geometry) {
    double worst = 0;
    for (size_t i = 0; i < geometry.placed.size(); ++i) {
      if (!geometry.placed[i]) continue;
      worst = std::max(worst, std::abs(static_cast<double>(geometry.points[3 * i + 2] + geometry.points[3 * i])));
    }
    return worst;
  };
  EXPECT_GT(off_slope(g), 5.0);  // the edge's distance: 7 mm above the slope at the last placed pixel
  const std::vector<uint64_t> visible_before = g.visible;
  auto refilled = RefillGeometry(bvh, camera, light, normals, options, &g);
  ASSERT_TRUE(refilled.ok()) << refilled.status();
  EXPECT_EQ(*refilled, 8 * h);
  // Within 0.1 mm: the crease lies between two pixels, and the first one past it is placed across the mean of the two
  // normals (22.5 degrees: 0.09 mm above the slope); every later one follows the slope from there.
  EXPECT_LT(off_slope(g), 0.1);
  // The mesh's own pixels did not move; the placed ones' shadows were traced again from their new points (the plane
  // now lies above them and hides the units low on the other side).
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < 10; ++x) EXPECT_NEAR(g.points[3 * (y * w + x) + 2], 0, 1e-3);
  }
  EXPECT_NE(g.visible, visible_before);
  // Without normals there is nothing to follow: the neighbours' distance stays.
  Image none(w, h, 3);
  PixelGeometry flat = TraceGeometry(bvh, camera, w, h, light, 2, 1);
  ASSERT_TRUE(FillGeometry(bvh, camera, light, frames, options, &flat).ok());
  const std::vector<float> before = flat.points;
  ASSERT_TRUE(RefillGeometry(bvh, camera, light, none, options, &flat).ok());
  for (size_t i = 0; i < before.size(); ++i) {
    ASSERT_EQ(std::isnan(flat.points[i]), std::isnan(before[i])) << i;
    if (!std::isnan(before[i])) {
      EXPECT_NEAR(flat.points[i], before[i], 1e-3) << i;
    }
  }
  options.geometry_refill_passes = 5;
  EXPECT_THAT(std::string(options.Validate().message()), ::testing::HasSubstr("geometry_refill_passes"));
}

// A jump in depth (a chin over the neck): the near surface turns down at its edge and the far one, 40 mm behind, is
// seen beside it. The pixels between the mesh's two parts are placed from the side whose normals agree with theirs:
// the far surface's pixels are not grown from the near side across the jump.
TEST(PhotometricTest, RefilledPixelsAreNotGrownAcrossAJumpInDepth) {
  const LightModel light = ShippedLight();
  TriangleMesh m;  // the near plane z = 0 for x < -4, the far plane z = -40 for x > 8
  m.positions = {{-50, -50, 0}, {-4, -50, 0},   {-4, 50, 0},   {-50, 50, 0},
                 {8, -50, -40}, {50, -50, -40}, {50, 50, -40}, {8, 50, -40}};
  m.triangles = {{0, 1, 2}, {0, 2, 3}, {4, 5, 6}, {4, 6, 7}};
  const MeshBvh bvh(m);
  const int w = 20;  // pixels 1 mm apart at z = 0, x = -9.5 .. 9.5
  const PhotometricCamera camera = RowsFromAbove(w);
  const std::vector<Image> frames = EvenFrames(light, w);
  PhotometricOptions options;
  options.threads = 1;
  options.geometry_fill_px = 8;
  PixelGeometry g = TraceGeometry(bvh, camera, w, 1, light, 2, 1);
  auto filled = FillGeometry(bvh, camera, light, frames, options, &g);
  ASSERT_TRUE(filled.ok()) << filled.status();
  ASSERT_EQ(*filled, 12);  // x = -3.5 .. 7.5
  // Up everywhere but where the near surface turns down towards its edge (x = -1.5, -0.5: 60 degrees).
  Image normals(w, 1, 3);
  const Eigen::Vector3f up(0, 0, 1), down(std::sin(M_PI / 3), 0, std::cos(M_PI / 3));
  for (int x = 0; x < w; ++x) std::copy_n((x == 8 || x == 9 ? down : up).data(), 3, normals.at(x, 0));
  ASSERT_TRUE(RefillGeometry(bvh, camera, light, normals, options, &g).ok());
  for (int x = 10; x < 18; ++x) EXPECT_NEAR(g.points[3 * x + 2], -40, 0.05) << "x = " << x - 9.5;
  for (int x = 6; x < 8; ++x) EXPECT_NEAR(g.points[3 * x + 2], 0, 0.05) << "x = " << x - 9.5;
}

// A reconstruction with a hole: the ray through it meets the inside of the far side of the head. The pixel is left
// uncovered (for FillGeometry), whichever way the mesh is wound.
TEST(PhotometricTest, ARayThroughAHoleInTheMeshIsNotTakenForTheSurface) {
  const LightModel light = ShippedLight();
  // A slab's front (z = 0, facing +z) with a 2 mm hole about x = 0, and its back (z = -50, facing -z).
  TriangleMesh m;
  m.positions = {{-50, -50, 0},   {-1, -50, 0},   {-1, 50, 0},   {-50, 50, 0},     // front, x < -1
                 {1, -50, 0},     {50, -50, 0},   {50, 50, 0},   {1, 50, 0},       // front, x > 1
                 {-50, -50, -50}, {50, -50, -50}, {50, 50, -50}, {-50, 50, -50}};  // back
  m.triangles = {{0, 1, 2}, {0, 2, 3}, {4, 5, 6}, {4, 6, 7}, {8, 10, 9}, {8, 11, 10}};
  PhotometricCamera camera;
  camera.position_mm = {0, 0, 1000};
  for (int x = 0; x < 7; ++x) {
    camera.rays.push_back((Eigen::Vector3d(1.5 * (x - 3), 0, 0) - camera.position_mm).normalized().cast<float>());
  }
  for (bool flipped : {false, true}) {
    SCOPED_TRACE(flipped ? "wound clockwise" : "wound counter-clockwise");
    TriangleMesh mesh = m;
    if (flipped) {
      for (auto& t : mesh.triangles) std::swap(t[1], t[2]);
    }
    const MeshBvh bvh(mesh);
    const PixelGeometry g = TraceGeometry(bvh, camera, 7, 1, light, 2, 1);
    for (int x = 0; x < 7; ++x) {
      EXPECT_EQ(g.Covers(static_cast<size_t>(x)), x != 3) << x;
      if (x != 3) {
        EXPECT_NEAR(g.points[3 * x + 2], 0, 1e-3) << x;
      }
    }
  }
}

}  // namespace
}  // namespace stage::processing
