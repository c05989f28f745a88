// Light transport against independent computations: a brute-force per-pixel, per-LED reference written separately
// here; the continuous-dome irradiance of a Lambertian sphere under gradient patterns; the polarization model.
#include "stage/sim/light_transport.h"

#include <Eigen/Geometry>
#include <cmath>
#include <cstdio>
#include <map>
#include <random>

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/sim/board.h"
#include "stage/sim/mesh.h"

namespace stage::sim {
namespace {

v1::CameraConfig Camera(const Eigen::Vector3d& position, int width = 160, int height = 120) {
  v1::CameraConfig c;
  c.set_id("cam");
  c.set_width(width);
  c.set_height(height);
  c.mutable_intrinsics()->set_focal_length_mm(35);
  c.mutable_intrinsics()->set_pixel_size_um(80);
  for (double k : {-0.08, 0.02, 0.001, -0.0005, 0.0}) c.mutable_intrinsics()->add_distortion(k);
  auto* pose = c.mutable_pose();
  pose->mutable_position_mm()->set_x(position.x());
  pose->mutable_position_mm()->set_y(position.y());
  pose->mutable_position_mm()->set_z(position.z());
  pose->mutable_up()->set_y(1);
  return c;
}

// ---- the reference: its own intersection, visibility and BRDF, in double precision ----------------------------

struct RefSurface {
  bool hit = false;
  Eigen::Vector3d p, n;
};

RefSurface RefSphere(const Eigen::Vector3d& o, const Eigen::Vector3d& d, const Eigen::Vector3d& c, double r) {
  // Solve |o + t d - c| = r for the nearest t > 0 by the quadratic formula in its textbook form.
  const double A = d.dot(d), B = 2 * d.dot(o - c), C = (o - c).dot(o - c) - r * r;
  const double disc = B * B - 4 * A * C;
  RefSurface s;
  if (disc < 0) return s;
  const double t = (-B - std::sqrt(disc)) / (2 * A);
  if (t <= 0) return s;
  s.hit = true;
  s.p = o + t * d;
  s.n = (s.p - c) / r;
  return s;
}

double RefGgx(double alpha, const Eigen::Vector3d& n, const Eigen::Vector3d& h) {
  const double cos_t = n.dot(h);
  if (cos_t <= 0) return 0;
  const double tan2 = (1 - cos_t * cos_t) / (cos_t * cos_t);
  const double a2 = alpha * alpha;
  // Walter et al. 2007, eq. 33, written in terms of tan(theta_m).
  return a2 / (M_PI * std::pow(cos_t, 4) * std::pow(a2 + tan2, 2));
}

double RefG1(double alpha, const Eigen::Vector3d& n, const Eigen::Vector3d& x) {
  const double c = n.dot(x);
  if (c <= 0) return 0;
  const double tan2 = (1 - c * c) / (c * c);
  // Walter et al. 2007, eq. 34.
  return 2 / (1 + std::sqrt(1 + alpha * alpha * tan2));
}

// Radiance (RGB) of one pixel under one exposure, LED by LED.
Eigen::Vector3d RefRadiance(const RefSurface& s, const Eigen::Vector3d& eye, const Material& m, const Dome& dome,
                            const EmitterLevels& levels, double leakage) {
  Eigen::Vector3d out = Eigen::Vector3d::Zero();
  const Eigen::Vector3d v = (eye - s.p).normalized();
  for (size_t l = 0; l < dome.units.size(); ++l) {
    const Eigen::Vector3d to = dome.units[l].position - s.p;
    const Eigen::Vector3d w = to.normalized();
    if (s.n.dot(w) <= 0) continue;  // a convex sphere: the LED is visible exactly when it is above the horizon
    const double e = dome.units[l].intensity / to.squaredNorm() * s.n.dot(w);
    const double cross = levels.cross[static_cast<Eigen::Index>(l)];
    const double parallel = levels.parallel[static_cast<Eigen::Index>(l)];
    const Eigen::Vector3d albedo = m.albedo.cast<double>();
    out += 0.5 * (cross + parallel) * albedo / M_PI * e;
    if (s.n.dot(v) > 0) {
      const Eigen::Vector3d h = (w + v).normalized();
      const double alpha = m.roughness;
      const double brdf = m.specular * RefGgx(alpha, s.n, h) * RefG1(alpha, s.n, w) * RefG1(alpha, s.n, v) /
                          (4 * s.n.dot(w) * s.n.dot(v));
      out += Eigen::Vector3d::Constant((parallel + leakage * cross) * brdf * e);
    }
  }
  return out;
}

TEST(LightTransportTest, MatchesABruteForceReferenceOnRandomPoses) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  double worst = 0;
  for (int trial = 0; trial < 4; ++trial) {
    std::vector<Eigen::Vector3d> dirs;
    for (int i = 0; i < 60; ++i) dirs.push_back(Eigen::Vector3d(u(rng), u(rng), u(rng)).normalized());
    Dome d = Dome::FromDirections(dirs, 900 + 200 * (u(rng) + 1));
    for (auto& unit : d.units) unit.intensity = 1e6 * (1.2 + u(rng));
    const Eigen::Vector3d center(30 * u(rng), 30 * u(rng), 30 * u(rng));
    const double radius = 80 + 20 * u(rng);
    Material m{Eigen::Vector3f(0.3f + 0.2f * float(u(rng)), 0.4f, 0.5f), 0.04f + 0.02f * float(u(rng)),
               0.25f + 0.1f * float(u(rng))};
    SphereSubject sphere(center.cast<float>(), static_cast<float>(radius), m);
    const Eigen::Vector3d eye = Eigen::Vector3d(u(rng), 0.3 * u(rng), 1).normalized() * 700;
    v1::CameraConfig config = Camera(eye);
    config.mutable_pose()->mutable_look_at_mm()->set_x(center.x());
    config.mutable_pose()->mutable_look_at_mm()->set_y(center.y());
    config.mutable_pose()->mutable_look_at_mm()->set_z(center.z());
    auto camera = CameraModel::FromConfig(config, 1.0);
    ASSERT_TRUE(camera.ok()) << camera.status();
    PixelResponses responses = ComputeResponses(*camera, sphere, d);
    ASSERT_GT(responses.pixels.size(), 1000u);
    EmitterLevels levels{Eigen::VectorXf(60), Eigen::VectorXf(60)};
    for (int l = 0; l < 60; ++l) {
      levels.cross[l] = static_cast<float>(0.5 + 0.5 * u(rng));
      levels.parallel[l] = static_cast<float>(0.5 + 0.5 * u(rng));
    }
    const float leakage = 0.02f;
    const std::vector<float> image = RenderRadiance(responses, levels, leakage);
    const std::vector<Eigen::Vector3f> rays = camera->PixelRays();
    int compared = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
      RefSurface s = RefSphere(eye, rays[i].cast<double>(), center, radius);
      const Eigen::Vector3d got(image[3 * i], image[3 * i + 1], image[3 * i + 2]);
      if (!s.hit) {
        EXPECT_EQ(got.norm(), 0) << i;
        continue;
      }
      const Eigen::Vector3d want = RefRadiance(s, eye, m, d, levels, leakage);
      if (want.norm() < 1e-12) continue;
      const double rel = (got - want).norm() / want.norm();
      worst = std::max(worst, rel);
      ++compared;
    }
    EXPECT_GT(compared, 1000);
  }
  std::printf("worst relative difference from the brute-force reference: %.2e\n", worst);
  EXPECT_LT(worst, 1e-4);
}

// A Lambertian sphere under a first-order gradient approaches the continuous dome's closed form as the dome gets
// denser: radiance = albedo/2 * (1/2 + n_x/3) for L(w) = (1 + w_x)/2 over the whole sphere (half passes the analyzer).
// Supersampled pixels integrate their area: an edge pixel is partly covered, the sphere's total light is what one ray
// a pixel gives (to the edge's quantization), and the pixels inside agree with the single ray through their centre.
TEST(LightTransportTest, SupersampledPixelsIntegrateTheirArea) {
  const Dome d = Dome::FromDirections(FibonacciSphere(64), 1000, 1e6);
  SphereSubject sphere(Eigen::Vector3f::Zero(), 30, Material{});  // about 38 pixels across
  auto camera = CameraModel::FromConfig(Camera({0, 0, 700}, 64, 48), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  const PixelResponses one = ComputeResponses(*camera, sphere, d, 0, 1);
  const PixelResponses four = ComputeResponses(*camera, sphere, d, 0, 4);
  EXPECT_GT(four.pixels.size(), one.pixels.size());  // the rim catches more pixels partly
  std::map<int32_t, double> sum_one;
  for (size_t i = 0; i < one.pixels.size(); ++i) sum_one[one.pixels[i]] = one.diffuse.row(i).sum();
  double total_one = 0, total_four = 0;
  int partial = 0, inside = 0;
  for (const auto& [pixel, v] : sum_one) total_one += v;
  for (size_t i = 0; i < four.pixels.size(); ++i) {
    const double v = four.diffuse.row(static_cast<Eigen::Index>(i)).sum();
    total_four += v;
    const int32_t p = four.pixels[i];
    // A pixel whose four neighbours are all on the sphere is inside: its light is smooth across it.
    const bool interior = sum_one.count(p) && sum_one.count(p - 1) && sum_one.count(p + 1) && sum_one.count(p - 64) &&
                          sum_one.count(p + 64);
    if (interior) {
      EXPECT_NEAR(v, sum_one[p], 0.02 * sum_one[p]) << p;
      ++inside;
    } else if (!sum_one.count(p)) {
      ++partial;  // covered by some of its rays only
    }
  }
  EXPECT_GT(inside, 100);
  EXPECT_GT(partial, 10);
  EXPECT_NEAR(total_four, total_one, 0.03 * total_one);
}

// A sphere printed black for x < 0.2 mm and white beyond (the edge a third of a pixel off the pixels' boundary).
class HalfPrintedSphere final : public Subject {
 public:
  Hit Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const override {
    Hit h = sphere_.Intersect(origin, direction);
    if (h.hit) h.material.albedo = Eigen::Vector3f::Constant(h.point.x() < 0.2f ? 0.0f : 1.0f);
    return h;
  }
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const override {
    return sphere_.Occluded(from, to);
  }

 private:
  SphereSubject sphere_{Eigen::Vector3f::Zero(), 30, Material{}};
};

// With texture samples, a pixel's albedo averages its area (the print's edge falls partly into the pixels it crosses)
// while its lighting stays what its lighting rays give.
TEST(LightTransportTest, TextureSamplesAverageThePrintNotTheLighting) {
  const Dome d = Dome::FromDirections(FibonacciSphere(64), 1000, 1e6);
  const HalfPrintedSphere subject;
  auto camera = CameraModel::FromConfig(Camera({0, 0, 700}, 64, 48), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  const PixelResponses one = ComputeResponses(*camera, subject, d, 0, 1);
  const PixelResponses textured = ComputeResponses(*camera, subject, d, 0, 1, nullptr, 8);
  ASSERT_EQ(one.pixels, textured.pixels);
  EXPECT_EQ((one.diffuse - textured.diffuse).cwiseAbs().maxCoeff(), 0.0f);
  int grey = 0;
  for (size_t i = 0; i < one.pixels.size(); ++i) {
    const float a = textured.albedo[i].x();
    if (a > 0.05f && a < 0.95f) {
      ++grey;  // the edge at x = 0 crosses this pixel
      const int column = one.pixels[i] % 64;
      EXPECT_EQ(column, 32) << one.pixels[i];
    } else {
      EXPECT_NEAR(a, one.albedo[i].x(), 0.05f) << one.pixels[i];
    }
  }
  EXPECT_GT(grey, 20);  // one column of the ~38 rows the sphere covers, about a third black
  const AreaAlbedo area = TraceAreaAlbedo(*camera, subject, 8);
  EXPECT_EQ(area.rays[24 * 64 + 32], 64);  // inside the sphere: every ray meets it
  EXPECT_EQ(area.rays[0], 0);
}

// A mesh's albedo alone (what texture samples ask for: no normals, no detail) is its Intersect's, to the bit, on the
// board's print and on the head's skin maps; and the texture samples of the lit pixels alone are the whole image's.
TEST(LightTransportTest, AMeshsAlbedoAloneIsItsIntersectionsAlbedo) {
  auto camera = CameraModel::FromConfig(Camera({40, 20, 700}, 96, 72), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.subject.kind=charuco"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto board = BoardModel::Create(rig->rig.sim().subject().board());
  ASSERT_TRUE(board.ok()) << board.status();
  HeadPose pose;
  pose.rotation_deg = Eigen::Vector3f(30, 15, 5);
  const auto head_model = HeadModel::Procedural(1, 48, HeadShape());
  const std::unique_ptr<MeshSubject> plate = (*board)->Posed(pose);
  const std::unique_ptr<MeshSubject> head = head_model->Posed(pose);
  const Eigen::Vector3f origin = camera->position().cast<float>();
  for (const MeshSubject* subject : {plate.get(), head.get()}) {
    int hits = 0, colours = 0;
    Eigen::Vector3f last = Eigen::Vector3f::Constant(-1);
    for (const double offset : {0.0, 0.3}) {
      for (const Eigen::Vector3f& ray : camera->PixelRays(offset, -offset)) {
        const Hit h = subject->Intersect(origin, ray);
        Eigen::Vector3f albedo = Eigen::Vector3f::Constant(-1);
        ASSERT_EQ(subject->AlbedoAt(origin, ray, &albedo), h.hit);
        if (!h.hit) continue;
        ++hits;
        ASSERT_EQ(albedo, h.material.albedo);
        colours += albedo != last;
        last = albedo;
      }
    }
    EXPECT_GT(hits, 1000);
    EXPECT_GT(colours, 50);  // a print or a skin, not one colour
  }
  const PixelResponses lit = ComputeResponses(*camera, *head, Dome::FromDirections(FibonacciSphere(16), 1000, 1e6));
  const AreaAlbedo whole = TraceAreaAlbedo(*camera, *head, 3);
  CameraRays rays(*camera);
  const AreaAlbedo some = TraceAreaAlbedo(rays, *head, 3, 0, nullptr, &lit.pixels);
  for (const int32_t p : lit.pixels) {
    EXPECT_EQ(some.albedo[static_cast<size_t>(p)], whole.albedo[static_cast<size_t>(p)]) << p;
    EXPECT_EQ(some.rays[static_cast<size_t>(p)], whole.rays[static_cast<size_t>(p)]) << p;
  }
  const auto met = [](const AreaAlbedo& a) {
    return std::count_if(a.rays.begin(), a.rays.end(), [](int n) { return n > 0; });
  };
  EXPECT_GT(lit.pixels.size(), 500u);
  EXPECT_EQ(met(some), static_cast<std::ptrdiff_t>(lit.pixels.size()));
  EXPECT_GT(met(whole), met(some));  // the rim's pixels that only some of their rays meet
}

// A camera's rays are the camera model's, undistorted once per offset and handed out again while they fit the budget;
// responses through kept rays are the same to the bit, frame after frame.
TEST(LightTransportTest, CameraRaysAreTheModelsAndKeptWithinTheirBudget) {
  auto camera = CameraModel::FromConfig(Camera({0, 0, 700}, 64, 48), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  const size_t one = size_t{64} * 48 * sizeof(Eigen::Vector3f);
  CameraRays rays(*camera, 2 * one);
  const auto centre = rays.At(0, 0);
  EXPECT_EQ(*centre, camera->PixelRays(0, 0));
  EXPECT_EQ(rays.At(0, 0), centre);  // kept
  const auto shifted = rays.At(0.25, -0.25);
  EXPECT_EQ(*shifted, camera->PixelRays(0.25, -0.25));
  EXPECT_NE(*shifted, *centre);
  const auto third = rays.At(-0.25, 0.25);  // over the budget: computed, not kept
  EXPECT_EQ(*third, camera->PixelRays(-0.25, 0.25));
  EXPECT_NE(rays.At(-0.25, 0.25), third);
  EXPECT_EQ(rays.At(0.25, -0.25), shifted);

  const Dome d = Dome::FromDirections(FibonacciSphere(64), 1000, 1e6);
  const HalfPrintedSphere subject;
  const PixelResponses fresh = ComputeResponses(*camera, subject, d, 0, 2, nullptr, 4);
  for (int frame = 0; frame < 2; ++frame) {
    const PixelResponses kept = ComputeResponses(rays, subject, d, 0, 2, nullptr, 4);
    ASSERT_EQ(kept.pixels, fresh.pixels);
    EXPECT_EQ((kept.diffuse - fresh.diffuse).cwiseAbs().maxCoeff(), 0.0f);
    EXPECT_EQ((kept.specular - fresh.specular).cwiseAbs().maxCoeff(), 0.0f);
    EXPECT_EQ(kept.albedo, fresh.albedo);
  }
}

// A subject that says it is not convex, whatever it is: the renderer traces its shadow rays.
class Traced final : public Subject {
 public:
  explicit Traced(const Subject& s) : s_(s) {}
  Hit Intersect(const Eigen::Vector3f& o, const Eigen::Vector3f& d) const override { return s_.Intersect(o, d); }
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const override { return s_.Occluded(from, to); }

 private:
  const Subject& s_;
};

// A convex subject is rendered without shadow rays: on a sphere the same responses, to the bit, as with them; on the
// calibration board's plate (two faces, open at the rim) the same for every pixel of its printed face, whichever way
// it is turned. The head is not taken for convex.
TEST(LightTransportTest, AConvexSubjectNeedsNoShadowRays) {
  const Dome d = Dome::FromDirections(FibonacciSphere(128), 1000, 1e6);
  auto camera = CameraModel::FromConfig(Camera({0, 0, 1500}, 96, 72), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  const SphereSubject sphere(Eigen::Vector3f(10, -5, 20), 90, Material{});
  ASSERT_TRUE(sphere.Convex());
  const PixelResponses fast_sphere = ComputeResponses(*camera, sphere, d, 0, 2);
  const PixelResponses slow_sphere = ComputeResponses(*camera, Traced(sphere), d, 0, 2);
  ASSERT_EQ(fast_sphere.pixels, slow_sphere.pixels);
  EXPECT_EQ((fast_sphere.diffuse - slow_sphere.diffuse).cwiseAbs().maxCoeff(), 0.0f);
  EXPECT_EQ((fast_sphere.specular - slow_sphere.specular).cwiseAbs().maxCoeff(), 0.0f);

  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.subject.kind=charuco"});  // the rig's board, defaults applied
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto board = BoardModel::Create(rig->rig.sim().subject().board());
  ASSERT_TRUE(board.ok()) << board.status();
  for (const float yaw : {0.0f, 50.0f, -80.0f}) {
    HeadPose pose;
    pose.rotation_deg = Eigen::Vector3f(yaw, 20, 10);
    const std::unique_ptr<MeshSubject> plate = (*board)->Posed(pose);
    ASSERT_TRUE(plate->Convex());
    // One ray a pixel: its row is that ray's hit alone.
    const PixelResponses fast = ComputeResponses(*camera, *plate, d, 0, 1);
    const PixelResponses slow = ComputeResponses(*camera, Traced(*plate), d, 0, 1);
    ASSERT_EQ(fast.pixels, slow.pixels);
    // The printed face's outward normal (from the back's corner to the face's; a ray past the rim may meet the face
    // from inside the plate).
    const TriangleMesh& m = plate->mesh();
    const Eigen::Vector3f out = (m.positions[0] - m.positions[4]).normalized();
    int printed = 0, differ = 0;
    for (size_t i = 0; i < fast.pixels.size(); ++i) {
      const auto row = static_cast<Eigen::Index>(i);
      const bool same =
          fast.diffuse.row(row) == slow.diffuse.row(row) && fast.specular.row(row) == slow.specular.row(row);
      differ += !same;
      if (fast.hits[i].part == 0 && fast.hits[i].geometric_normal.dot(out) > 0) {
        ++printed;
        EXPECT_TRUE(same) << "yaw " << yaw << ", pixel " << fast.pixels[i];
      }
    }
    EXPECT_GT(printed, 500) << "yaw " << yaw;
    std::printf(
        "yaw %+.0f deg: %d pixels see the print, %d of %zu differ (the plate's back, or its face seen past the rim "
        "from inside)\n",
        yaw, printed, differ, fast.pixels.size());
  }
  EXPECT_FALSE(HeadModel::Procedural(1, 32, HeadShape())->Posed(HeadPose())->Convex());
}

// A subject whose every shadow ray gets through; `convex` says whether the renderer may skip them.
class Unshadowed final : public Subject {
 public:
  Unshadowed(const Subject& s, bool convex) : s_(s), convex_(convex) {}
  Hit Intersect(const Eigen::Vector3f& o, const Eigen::Vector3f& d) const override { return s_.Intersect(o, d); }
  bool Occluded(const Eigen::Vector3f&, const Eigen::Vector3f&) const override { return false; }
  bool Convex() const override { return convex_; }

 private:
  const Subject& s_;
  bool convex_;
};

// The head's shadow rays traced together (MeshSubject::OccludedMany: a block of neighbouring pixels towards one unit
// after another, as Embree's packets) give the responses, to the bit, that they give traced one at a time; every
// response is its unshadowed one, or zero where the head blocks that pixel's own segment to that unit (asked of the
// head one segment at a time, apart from the renderer's blocks); and the head does shadow itself.
TEST(LightTransportTest, ShadowRaysTracedTogetherGiveTheResponsesOfOneAtATime) {
  const Dome d = Dome::FromDirections(FibonacciSphere(128), 1000, 1e6);
  auto camera = CameraModel::FromConfig(Camera({150, 40, 600}, 120, 90), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  HeadPose pose;
  pose.rotation_deg = Eigen::Vector3f(25, -10, 5);
  const auto model = HeadModel::Procedural(1, 64, HeadShape());  // outlives its posed meshes (their surface)
  const std::unique_ptr<MeshSubject> head = model->Posed(pose);
  ASSERT_FALSE(head->Convex());
  for (const int supersample : {1, 2}) {
    const PixelResponses together = ComputeResponses(*camera, *head, d, 2, supersample);
    const PixelResponses one = ComputeResponses(*camera, Traced(*head), d, 2, supersample);
    const PixelResponses unshadowed = ComputeResponses(*camera, Unshadowed(*head, false), d, 2, supersample);
    const PixelResponses untraced = ComputeResponses(*camera, Unshadowed(*head, true), d, 2, supersample);
    ASSERT_EQ(together.pixels, one.pixels);
    ASSERT_GT(together.pixels.size(), 1000u);
    EXPECT_EQ((together.diffuse - one.diffuse).cwiseAbs().maxCoeff(), 0.0f) << supersample;
    EXPECT_EQ((together.specular - one.specular).cwiseAbs().maxCoeff(), 0.0f) << supersample;
    // No shadows with or without their rays: the same units light each hit.
    ASSERT_EQ(untraced.pixels, unshadowed.pixels);
    EXPECT_EQ((untraced.diffuse - unshadowed.diffuse).cwiseAbs().maxCoeff(), 0.0f) << supersample;
    EXPECT_EQ((untraced.specular - unshadowed.specular).cwiseAbs().maxCoeff(), 0.0f) << supersample;
    // The head shadows itself: some pixels lose some units' light.
    ASSERT_EQ(together.pixels, unshadowed.pixels);
    EXPECT_GT(((unshadowed.diffuse - together.diffuse).array() > 0).count(), 1000) << supersample;
    if (supersample != 1) continue;
    // One ray a pixel: its row is its hit's alone, each entry its unshadowed one unless that hit's segment is blocked.
    int blocked = 0, wrong = 0;
    for (size_t i = 0; i < together.pixels.size(); ++i) {
      const Hit& h = together.hits[i];
      const Eigen::Vector3f start = h.point + 1e-3f * h.geometric_normal;
      for (size_t l = 0; l < d.units.size(); ++l) {
        const auto row = static_cast<Eigen::Index>(i), col = static_cast<Eigen::Index>(l);
        const float open = unshadowed.diffuse(row, col);
        if (open == 0) {
          wrong += together.diffuse(row, col) != 0;
          continue;
        }
        const bool shadowed = head->Occluded(start, d.units[l].position.cast<float>());
        blocked += shadowed;
        wrong += together.diffuse(row, col) != (shadowed ? 0.0f : open);
      }
    }
    EXPECT_EQ(wrong, 0);
    EXPECT_GT(blocked, 1000);
  }
}

// Responses computed for a few exposures alone (ExposureBasis: each pixel's sums under them) render those exposures as
// the responses to every unit do, to float rounding: on the head, which shadows itself, with 2 x 2 rays a pixel and
// its texture averaged over 3 x 3. Any other exposure, or another leakage, is refused by name, not rendered wrong.
TEST(LightTransportTest, ResponsesForAFewExposuresRenderThemAsEveryUnitsDo) {
  const Dome d = Dome::FromDirections(FibonacciSphere(96), 1000, 1e6);
  auto camera = CameraModel::FromConfig(Camera({120, 30, 600}, 96, 72), 1.0);
  ASSERT_TRUE(camera.ok()) << camera.status();
  HeadPose pose;
  pose.rotation_deg = Eigen::Vector3f(20, -15, 0);
  const auto model = HeadModel::Procedural(1, 48, HeadShape());
  const std::unique_ptr<MeshSubject> head = model->Posed(pose);
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0, 1);
  const auto n = static_cast<Eigen::Index>(d.units.size());
  EmitterLevels full{Eigen::VectorXf::Zero(n), Eigen::VectorXf::Ones(n)};
  EmitterLevels mixed{Eigen::VectorXf(n), Eigen::VectorXf(n)};
  for (Eigen::Index l = 0; l < n; ++l) {
    mixed.cross[l] = u(rng);
    mixed.parallel[l] = u(rng);
  }
  const float leakage = 0.03f;
  auto basis = std::make_shared<ExposureBasis>();
  basis->levels = {full, mixed};
  basis->leakage = leakage;
  const PixelResponses every = ComputeResponses(*camera, *head, d, 2, 2, nullptr, 3);
  const PixelResponses few = ComputeResponses(*camera, *head, d, 2, 2, nullptr, 3, basis);
  ASSERT_EQ(few.pixels, every.pixels);
  ASSERT_GT(few.pixels.size(), 1500u);
  EXPECT_EQ(few.diffuse.cols(), 2);
  for (const EmitterLevels& levels : {full, mixed}) {
    const std::vector<float> want = RenderRadiance(every, levels, leakage);
    const absl::StatusOr<std::vector<float>> got = RenderRadianceOf(few, levels, leakage);
    ASSERT_TRUE(got.ok()) << got.status();
    double worst = 0, brightest = 0;
    for (size_t i = 0; i < want.size(); ++i) {
      worst = std::max(worst, static_cast<double>(std::abs((*got)[i] - want[i])));
      brightest = std::max(brightest, static_cast<double>(want[i]));
    }
    EXPECT_GT(brightest, 0);
    EXPECT_LT(worst, 1e-5 * brightest);
  }
  EmitterLevels other = mixed;
  other.cross[3] += 0.25f;
  const absl::StatusOr<std::vector<float>> refused = RenderRadianceOf(few, other, leakage);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("2 exposure(s)"), std::string::npos) << refused.status();
  EXPECT_FALSE(RenderRadianceOf(few, full, 2 * leakage).ok());
  EXPECT_EQ(basis->Find(mixed, leakage), 1);
}

TEST(LightTransportTest, LambertianSphereConvergesToTheContinuousDome) {
  const double far = 1e7;  // distant LEDs
  Material m{Eigen::Vector3f::Constant(0.8f), 0.0f, 0.3f};
  SphereSubject sphere(Eigen::Vector3f::Zero(), 100, m);
  auto camera = CameraModel::FromConfig(Camera({0, 0, 800}), 1.0);
  ASSERT_TRUE(camera.ok());
  std::vector<double> errors;
  for (int n : {64, 512, 4096}) {
    // Each unit stands for 4 pi / n steradians of the continuous dome.
    Dome dome = Dome::FromDirections(FibonacciSphere(n), far, far * far * 4 * M_PI / n);
    PixelResponses r = ComputeResponses(*camera, sphere, dome);
    EmitterLevels levels{Eigen::VectorXf::Zero(n), Eigen::VectorXf(n)};
    for (int l = 0; l < n; ++l) levels.parallel[l] = static_cast<float>((1 + dome.units[l].direction.x()) / 2);
    std::vector<float> image = RenderRadiance(r, levels, 0);
    double sum = 0;
    for (size_t i = 0; i < r.pixels.size(); ++i) {
      const double want = 0.8 / 2 * (0.5 + r.hits[i].normal.x() / 3.0);
      sum += std::abs(image[static_cast<size_t>(r.pixels[i]) * 3] - want) / want;
    }
    errors.push_back(sum / static_cast<double>(r.pixels.size()));
    std::printf("dome of %4d LEDs: mean relative error %.4f %%\n", n, errors.back() * 100);
  }
  EXPECT_LT(errors[1], errors[0]);
  EXPECT_LT(errors[2], errors[1]);
  EXPECT_LT(errors[2], 0.005);
}

TEST(LightTransportTest, CrossPolarizedSpecularIsDarkUpToTheLeakageAndParallelMinusCrossIsSpecular) {
  Dome dome = Dome::FromDirections(FibonacciSphere(200), 1000, 1e6);
  auto camera = CameraModel::FromConfig(Camera({0, 0, 700}), 1.0);
  ASSERT_TRUE(camera.ok());
  const Eigen::VectorXf full = Eigen::VectorXf::Ones(200), none = Eigen::VectorXf::Zero(200);
  // A specular-only material.
  SphereSubject shiny(Eigen::Vector3f::Zero(), 100, Material{Eigen::Vector3f::Zero(), 0.05f, 0.2f});
  PixelResponses r = ComputeResponses(*camera, shiny, dome);
  const float leakage = 0.01f;
  std::vector<float> cross = RenderRadiance(r, {full, none}, leakage);
  std::vector<float> parallel = RenderRadiance(r, {none, full}, leakage);
  int lit = 0;
  for (size_t i = 0; i < cross.size(); ++i) {
    if (parallel[i] <= 0) continue;
    ++lit;
    EXPECT_NEAR(cross[i], leakage * parallel[i], 1e-6f * parallel[i]) << i;
  }
  EXPECT_GT(lit, 1000);
  // Diffuse plus specular: parallel - cross = (1 - leakage) x the specular image, and = it exactly without leakage.
  SphereSubject skin(Eigen::Vector3f::Zero(), 100, Material{Eigen::Vector3f(0.6f, 0.4f, 0.3f), 0.04f, 0.3f});
  r = ComputeResponses(*camera, skin, dome);
  SphereSubject specular_only(Eigen::Vector3f::Zero(), 100, Material{Eigen::Vector3f::Zero(), 0.04f, 0.3f});
  PixelResponses rs = ComputeResponses(*camera, specular_only, dome);
  std::vector<float> spec = RenderRadiance(rs, {none, full}, 0);
  for (float leak : {0.0f, 0.02f}) {
    cross = RenderRadiance(r, {full, none}, leak);
    parallel = RenderRadiance(r, {none, full}, leak);
    for (size_t i = 0; i < spec.size(); ++i) {
      EXPECT_NEAR(parallel[i] - cross[i], (1 - leak) * spec[i], 1e-5f * (1 + parallel[i])) << i;
    }
  }
}

TEST(LightTransportTest, LeakageGrowsWithTheCameraAngle) {
  auto front = CameraModel::FromConfig(Camera({0, 0, 700}), 1.0);
  auto side = CameraModel::FromConfig(Camera({700, 0, 0}), 1.0);
  EXPECT_NEAR(CrossLeakage(*front, 0.01, 0.05), 0.01f, 1e-6f);
  EXPECT_NEAR(CrossLeakage(*side, 0.01, 0.05), 0.06f, 1e-6f);
}

}  // namespace
}  // namespace stage::sim
