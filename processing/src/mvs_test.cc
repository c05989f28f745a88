// Multi-view stereo against closed forms: the rig's 24 machine-vision cameras see a textured sphere and a textured
// plane, rendered here by exact ray intersection (the simulator's analytic sphere and plane are one uniform material:
// nothing for stereo to match, as on a real stage, where test targets are speckle-painted); the fused mesh must lie on
// the closed-form surface. Also: options are validated naming the field, neighbours are the nearest views, a view
// without neighbours is refused by name, the mesh trim keeps the largest piece inside the volume, and narrow holes
// are closed on the surface about them.
#include "stage/processing/mvs.h"

#include <Eigen/Geometry>
#include <cmath>
#include <functional>
#include <map>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mvs_internal.h"
#include "stage/common/rig.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

// A speckle texture of the point (mm): random-looking variation from a few millimetres to a few centimetres, as a
// painted test target has.
float Speckle(const Eigen::Vector3d& p) {
  double v = 0;
  const double f[4][3] = {{0.91, 0.37, 0.55}, {-0.42, 1.13, 0.71}, {0.63, -0.88, 1.07}, {1.31, 0.52, -0.94}};
  for (double scale : {0.08, 0.25, 0.7}) {
    for (int k = 0; k < 4; ++k) v += std::sin(scale * (f[k][0] * p.x() + f[k][1] * p.y() + f[k][2] * p.z()) + k);
  }
  return static_cast<float>(0.5 + 0.035 * v);
}

// The subject: where the ray from `o` along unit `d` meets it, and its normal there.
using Intersect =
    std::function<bool(const Eigen::Vector3d& o, const Eigen::Vector3d& d, double* t, Eigen::Vector3d* normal)>;

// Every machine-vision camera of the shipped rig at `scale`, seeing `subject` evenly lit (grey = its texture), as
// undistorted views.
std::vector<MvsView> RenderViews(const Intersect& subject, double scale) {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok()) << rig.status();
  std::vector<MvsView> views;
  for (const v1::CameraConfig& c : rig->rig.cameras()) {
    if (c.role() != v1::CAMERA_ROLE_MACHINE_VISION) continue;
    auto model = CameraModel::FromConfig(c, scale);
    EXPECT_TRUE(model.ok()) << model.status();
    MvsView v;
    v.id = c.id();
    v.width = model->width();
    v.height = model->height();
    v.fx = model->fx(), v.fy = model->fy(), v.cx = model->cx(), v.cy = model->cy();
    v.rotation = model->rotation();
    v.position = model->position();
    v.grey.assign(static_cast<size_t>(v.width) * v.height, 0.f);
    for (int y = 0; y < v.height; ++y) {
      for (int x = 0; x < v.width; ++x) {
        const Eigen::Vector3d d =
            (v.rotation.transpose() * Eigen::Vector3d((x - v.cx) / v.fx, (y - v.cy) / v.fy, 1)).normalized();
        double t = 0;
        Eigen::Vector3d n;
        if (!subject(v.position, d, &t, &n)) continue;
        // Lit evenly from every side (as the full-on pattern lights a subject): the same radiance to every camera.
        v.grey[static_cast<size_t>(y) * v.width + x] = static_cast<float>(100 * Speckle(v.position + t * d));
      }
    }
    views.push_back(std::move(v));
  }
  return views;
}

MvsOptions TestOptions() {
  MvsOptions o;
  o.threads = 2;
  return o;
}

TEST(MvsTest, ASphereIsReconstructedOnItsClosedForm) {
  const Eigen::Vector3d centre(5, -3, 8);
  const double radius = 90;
  const Intersect sphere = [&](const Eigen::Vector3d& o, const Eigen::Vector3d& d, double* t, Eigen::Vector3d* n) {
    const Eigen::Vector3d oc = o - centre;
    const double b = oc.dot(d), c = oc.squaredNorm() - radius * radius, disc = b * b - c;
    if (disc < 0) return false;
    *t = -b - std::sqrt(disc);
    *n = (o + *t * d - centre) / radius;
    return *t > 0;
  };
  // Scale 0.125: a pixel ~1.1 mm at the sphere.
  const std::vector<MvsView> views = RenderViews(sphere, 0.125);
  ASSERT_EQ(views.size(), 24u);
  auto f = ReconstructFrame(views, TestOptions());
  ASSERT_TRUE(f.ok()) << f.status();
  ASSERT_GT(f->mesh.positions.size(), 10000u);
  double sq = 0, worst = 0;
  for (const Eigen::Vector3f& p : f->mesh.positions) {
    const double e = (p.cast<double>() - centre).norm() - radius;
    sq += e * e;
    worst = std::max(worst, std::abs(e));
  }
  const double rms = std::sqrt(sq / static_cast<double>(f->mesh.positions.size()));
  // A pixel is ~1.1 mm here, so the coarse bar of the score applies. Measured: RMS 0.46 mm, worst 3.9 mm (at the rim
  // of what the cameras see); without the median of the coarser levels' depths 0.43 and 3.4.
  EXPECT_NEAR(f->pixel_mm, 1.1, 0.15);
  EXPECT_EQ(f->min_score, TestOptions().min_score);
  EXPECT_LT(rms, 0.6) << "worst " << worst;
  EXPECT_LT(worst, 5.0);
  // The cameras see all but the sphere's back and underside: most of its area is meshed.
  double area = 0;
  for (const auto& t : f->mesh.triangles) {
    area += 0.5 * (f->mesh.positions[t[1]] - f->mesh.positions[t[0]])
                      .cross(f->mesh.positions[t[2]] - f->mesh.positions[t[0]])
                      .norm();
  }
  EXPECT_GT(area, 0.5 * 4 * M_PI * radius * radius);
  // Every view's depths agree with the sphere's where they are kept.
  for (size_t i = 0; i < views.size(); ++i) {
    EXPECT_GT(f->views[i].consistent, f->views[i].foreground / 2) << views[i].id;
  }
}

TEST(MvsTest, APlaneIsReconstructedOnItsClosedForm) {
  // A plane through (0, 10, 20) facing the front cameras, tilted 20 degrees about x; a 260 mm disc of it.
  const Eigen::Vector3d normal =
      Eigen::AngleAxisd(20 * M_PI / 180, Eigen::Vector3d::UnitX()) * Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d point(0, 10, 20);
  const Intersect plane = [&](const Eigen::Vector3d& o, const Eigen::Vector3d& d, double* t, Eigen::Vector3d* n) {
    const double den = normal.dot(d);
    if (std::abs(den) < 1e-9) return false;
    *t = normal.dot(point - o) / den;
    *n = normal;
    return *t > 0 && (o + *t * d - point).norm() < 130;
  };
  const std::vector<MvsView> views = RenderViews(plane, 0.125);
  auto f = ReconstructFrame(views, TestOptions());
  ASSERT_TRUE(f.ok()) << f.status();
  ASSERT_GT(f->mesh.positions.size(), 5000u);
  double sq = 0;
  int64_t inner = 0;
  for (const Eigen::Vector3f& p : f->mesh.positions) {
    // Away from the disc's rim (where fusion rounds the edge off).
    if ((p.cast<double>() - point).norm() > 110) continue;
    const double e = normal.dot(p.cast<double>() - point);
    sq += e * e;
    ++inner;
  }
  ASSERT_GT(inner, 3000);
  // Measured: RMS 0.24 mm (cameras at the side see the disc nearly edge-on); 0.47 mm without the median of the
  // coarser levels' depths (a wrong coarse depth steers the finer sweeps).
  EXPECT_LT(std::sqrt(sq / static_cast<double>(inner)), 0.35);
}

TEST(MvsTest, OptionsAreCheckedByNameAndViewsWithoutNeighboursAreRefused) {
  MvsOptions o;
  EXPECT_TRUE(o.Validate().ok());
  o.window = 8;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("window 8"));
  o = MvsOptions();
  o.best_of = 5;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("best_of"));
  o = MvsOptions();
  o.image_scale = 0;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("image_scale"));
  o = MvsOptions();
  o.prior_median_radius = 9;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("prior_median_radius 9"));
  o = MvsOptions();
  o.fill_holes_mm = -1;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("fill_holes_mm"));
  o = MvsOptions();
  o.silhouette_grow_px = 17;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("silhouette_grow_px 17"));

  // Two views looking at each other's backs: no neighbour within 50 degrees.
  MvsView a, b;
  a.id = "front";
  b.id = "back";
  for (MvsView* v : {&a, &b}) {
    v->width = v->height = 32;
    v->fx = v->fy = 100;
    v->cx = v->cy = 15.5;
    v->grey.assign(32 * 32, 1.f);
  }
  a.position = {0, 0, 1000};
  a.rotation = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY()).toRotationMatrix();
  b.position = {0, 0, -1000};
  auto f = ReconstructFrame({a, b}, MvsOptions());
  ASSERT_FALSE(f.ok());
  EXPECT_THAT(std::string(f.status().message()), HasSubstr("view \"front\": no other view"));
}

TEST(MvsTest, TheTrimKeepsTheLargestPieceInsideTheVolume) {
  TriangleMesh m;
  // A big square (2 triangles) inside, a small triangle inside but apart, and one far outside.
  m.positions = {{0, 0, 0},   {50, 0, 0},  {50, 50, 0}, {0, 50, 0},  {-80, 0, 0},
                 {-79, 0, 0}, {-80, 1, 0}, {500, 0, 0}, {501, 0, 0}, {500, 1, 0}};
  m.triangles = {{0, 1, 2}, {0, 2, 3}, {4, 5, 6}, {7, 8, 9}};
  const TriangleMesh t = TrimToHead(m, Eigen::Vector3d::Zero(), 200);
  EXPECT_EQ(t.triangles.size(), 2u);
  EXPECT_EQ(t.positions.size(), 4u);
}

// A grid of `n` x `n` vertices `step` apart on the sphere of radius `r` about (0, 0, -r) (a cap about its top), less
// the triangles whose centre's (x, y) `cut` says.
TriangleMesh CapWithHoles(int n, float step, float r, const std::function<bool(const Eigen::Vector2f&)>& cut) {
  TriangleMesh m;
  auto on_sphere = [&](float x, float y) { return Eigen::Vector3f(x, y, std::sqrt(r * r - x * x - y * y) - r); };
  const float half = 0.5f * step * static_cast<float>(n - 1);
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) m.positions.push_back(on_sphere(i * step - half, j * step - half));
  }
  auto add = [&](int a, int b, int c) {
    if (!cut(((m.positions[a] + m.positions[b] + m.positions[c]) / 3).head<2>())) m.triangles.push_back({a, b, c});
  };
  for (int j = 0; j + 1 < n; ++j) {
    for (int i = 0; i + 1 < n; ++i) {
      const int a = j * n + i;
      add(a, a + 1, a + n + 1);
      add(a, a + n + 1, a + n);
    }
  }
  return m;
}

TEST(MvsTest, NarrowHolesAreClosedOnTheSurfaceTheyInterruptAndWideOnesAreLeft) {
  // A cap of a 60 mm sphere (a cheek's curvature), 0.25 mm edges, with a hole 2 mm across at the top, a crack 0.5 mm
  // wide and 8 mm long, and a hole 10 mm across.
  const float r = 60;
  TriangleMesh m = CapWithHoles(161, 0.25f, r, [](const Eigen::Vector2f& p) {
    return p.norm() < 1 || (std::abs(p.x() + 8) < 0.25f && std::abs(p.y()) < 4) ||
           (p - Eigen::Vector2f(10, 0)).norm() < 5;
  });
  const size_t vertices = m.positions.size(), before = m.triangles.size();
  const HoleFill filled = FillHoles(3, &m);
  EXPECT_EQ(filled.holes, 2);
  EXPECT_EQ(m.positions.size(), vertices);  // no vertex added
  // The disc's pi mm^2 and the crack's 4 mm^2, give or take the grid's steps.
  EXPECT_NEAR(filled.area_mm2, M_PI + 4, 1.5);
  // The patches lie on the sphere: a chord across 2 mm sags r^2 / 2R ~ 8 um.
  for (size_t t = before; t < m.triangles.size(); ++t) {
    const Eigen::Vector3f c =
        (m.positions[m.triangles[t][0]] + m.positions[m.triangles[t][1]] + m.positions[m.triangles[t][2]]) / 3;
    EXPECT_NEAR((c - Eigen::Vector3f(0, 0, -r)).norm(), r, 0.02) << t;
  }
  // The narrow holes are closed: rays down through them meet the mesh; the wide one is still open.
  const MeshBvh bvh(m);
  MeshHit hit;
  EXPECT_TRUE(bvh.Nearest({0.1f, 0.05f, 5}, {0, 0, -1}, 10, &hit));
  EXPECT_TRUE(bvh.Nearest({-8.01f, 2.9f, 5}, {0, 0, -1}, 10, &hit));
  EXPECT_FALSE(bvh.Nearest({10, 0, 5}, {0, 0, -1}, 10, &hit));
  // Closed consistently: no edge of three triangles, and each edge of two runs once each way.
  std::map<std::pair<int32_t, int32_t>, int> runs;
  for (const auto& t : m.triangles) {
    for (int k = 0; k < 3; ++k) ++runs[{t[k], t[(k + 1) % 3]}];
  }
  for (const auto& [edge, count] : runs) EXPECT_EQ(count, 1) << edge.first << " -> " << edge.second;
  // A limit of 0 closes nothing.
  TriangleMesh untouched = CapWithHoles(41, 0.25f, r, [](const Eigen::Vector2f& p) { return p.norm() < 1; });
  const size_t triangles = untouched.triangles.size();
  EXPECT_EQ(FillHoles(0, &untouched).holes, 0);
  EXPECT_EQ(untouched.triangles.size(), triangles);
}

}  // namespace
}  // namespace stage::processing
