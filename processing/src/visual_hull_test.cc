#include "stage/processing/visual_hull.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>

#include "test_cameras.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

// A `size`-pixel square camera `distance_mm` from the stage origin along `axis` (unit), looking at it.
CameraModel LookingAtOrigin(const Eigen::Vector3d& axis, double distance_mm, int size, double fx) {
  return CameraLookingAt(distance_mm * axis, Eigen::Vector3d::Zero(), size, size, fx);
}

// The silhouette of the sphere of `radius` mm about the origin through `camera`.
Silhouette OfSphere(const std::string& id, const CameraModel& camera, double radius) {
  Silhouette s{id, camera, std::vector<uint8_t>(static_cast<size_t>(camera.width()) * camera.height())};
  const std::vector<Eigen::Vector3f> rays = camera.PixelRays();
  for (size_t i = 0; i < rays.size(); ++i) {
    const Eigen::Vector3d d = rays[i].cast<double>(), o = camera.position();
    // The ray's nearest approach to the centre.
    s.inside[i] = (o - o.dot(d) * d).norm() <= radius;
  }
  return s;
}

TEST(SilhouetteMaskTest, ClosesHolesAndGrows) {
  const int w = 9, h = 7;
  std::vector<float> grey(w * h, 0.f);
  // A bright ring (rows 1-5, columns 2-6) around a dark pixel, and one bright pixel alone in a corner.
  for (int y = 1; y <= 5; ++y) {
    for (int x = 2; x <= 6; ++x) grey[y * w + x] = (x == 4 && y == 3) ? 0.f : 1.f;
  }
  grey[0] = 0.5f;
  const std::vector<uint8_t> mask = SilhouetteMask(grey, w, h, 0.5f, 0);
  EXPECT_EQ(mask[3 * w + 4], 1) << "the hole the background cannot reach is inside";
  EXPECT_EQ(mask[0], 1);
  EXPECT_EQ(mask[3 * w + 7], 0);
  EXPECT_EQ(mask[3 * w + 1], 0);
  const std::vector<uint8_t> grown = SilhouetteMask(grey, w, h, 0.5f, 1);
  EXPECT_EQ(grown[3 * w + 7], 1);
  EXPECT_EQ(grown[3 * w + 1], 1);
  EXPECT_EQ(grown[3 * w + 8], 0);
  // Below the bar nothing is inside.
  const std::vector<uint8_t> none = SilhouetteMask(grey, w, h, 2.f, 3);
  for (uint8_t v : none) ASSERT_EQ(v, 0);
  EXPECT_TRUE(SilhouetteMask(grey, w + 1, h, 0.5f, 0).empty()) << "an image of another size";
}

// Four views about a sphere: the hull holds the sphere, so a ray's first stretch inside it brackets the ray's chord of
// the sphere; a ray that passes the sphere's side by a fifth of its radius meets no hull.
TEST(VisualHullTest, HoldsTheSubjectAndBoundsARayThroughIt) {
  const double r = 50;
  std::vector<Silhouette> views;
  const Eigen::Vector3d axes[4] = {{0, 0, 1}, {1, 0, 0}, {-1, 0, 0}, Eigen::Vector3d(1, 0, 1).normalized()};
  for (int k = 0; k < 4; ++k) {
    views.push_back(OfSphere("v" + std::to_string(k), LookingAtOrigin(axes[k], 1000, 400, 2000), r));
  }
  const VisualHull hull(views);
  using Seen = VisualHull::Seen;
  EXPECT_EQ(hull.Judge({0, 0, 0}), Seen::kInside);
  EXPECT_EQ(hull.Judge({0, 49, 0}), Seen::kInside);
  EXPECT_EQ(hull.Judge({0, 0, 55}), Seen::kOutside);
  EXPECT_EQ(hull.Judge({60, 0, 0}), Seen::kOutside);
  // A point no view's image holds is not judged (the images hold +-100 mm about the origin).
  EXPECT_EQ(hull.Judge({0, 500, 0}), Seen::kByNone);

  // A ray from above at a slant, through the sphere off its centre. It comes into the views' images about 50 mm above
  // the sphere (y 100), then passes through air they see, then the sphere.
  const Eigen::Vector3d origin(30, 800, 10), target(10, 0, -5);
  const Eigen::Vector3d dir = (target - origin).normalized();
  const double b = origin.dot(dir), c = origin.squaredNorm() - r * r;
  const double entry = -b - std::sqrt(b * b - c), exit = -b + std::sqrt(b * b - c);
  double in = 0, out = 0;
  ASSERT_TRUE(hull.FirstSpan(origin, dir, entry - 100, entry + 100, 1, &in, &out));
  EXPECT_LE(in, entry + 0.1);
  EXPECT_GE(out, exit - 0.1);
  // Four views about the equator leave the hull loose at the poles, but not by more than the sphere's radius.
  EXPECT_GT(in, entry - r);
  EXPECT_LT(out, exit + r);
  bool entered = false;
  ASSERT_TRUE(hull.FirstSpan(origin, dir, entry - 40, entry + 100, 1, &in, &out, &entered));
  EXPECT_TRUE(entered);
  // Searched from inside, the stretch starts where the search does, and the ray was not seen to enter there.
  ASSERT_TRUE(hull.FirstSpan(origin, dir, entry + 5, entry + 100, 1, &in, &out, &entered));
  EXPECT_EQ(in, entry + 5);
  EXPECT_FALSE(entered);
  // A view whose image ends inside the sphere's outline (+-45 mm): a ray down the y axis goes from air it does not see
  // straight into the sphere. The unseen stretch widens the span, and the ray was not seen to enter where it begins.
  const VisualHull cropped({OfSphere("v0", LookingAtOrigin(axes[0], 1000, 180, 2000), r)});
  ASSERT_TRUE(cropped.FirstSpan({0, 800, 0}, {0, -1, 0}, 600, 1000, 1, &in, &out, &entered));
  EXPECT_EQ(in, 600);
  EXPECT_EQ(out, 1000);
  EXPECT_FALSE(entered);
  EXPECT_FALSE(cropped.FirstSpan({0, 800, 0}, {0, -1, 0}, 600, 700, 1, &in, &out)) << "seen by none";
  // A stretch of no length, and bad bounds.
  ASSERT_TRUE(hull.FirstSpan(origin, dir, entry + 5, entry + 5, 1, &in, &out));
  EXPECT_EQ(out, entry + 5);
  EXPECT_FALSE(hull.FirstSpan(origin, dir, entry, INFINITY, 1, &in, &out));
  EXPECT_FALSE(hull.FirstSpan(origin, dir, entry, entry + 10, 0, &in, &out));

  // A ray along z, a fifth of the radius past the sphere's side, over +-100 mm about the sphere: v1's silhouette holds
  // it where it passes the sphere (v1 looks at it from the side), v0's nowhere (it looks along it).
  EXPECT_FALSE(hull.FirstSpan({60, 0, 800}, {0, 0, -1}, 700, 900, 1, &in, &out));
  EXPECT_FALSE(hull.FirstSpan(origin, dir, entry - 40, entry - 20, 1, &in, &out)) << "the air above the sphere";
}

TEST(VisualHullTest, WritesAndReadsItsSilhouettes) {
  const std::string root = ::testing::TempDir() + "/visual-hull";
  std::filesystem::remove_all(root);
  std::vector<Silhouette> views = {OfSphere("mv-01", LookingAtOrigin({0, 0, 1}, 1000, 64, 600), 50),
                                   OfSphere("mv-02", LookingAtOrigin({1, 0, 0}, 1000, 64, 600), 50)};
  ASSERT_TRUE(VisualHull::Write(root + "/silhouette", views).ok());
  auto read = VisualHull::Read(root + "/silhouette");
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->views().size(), 2u);
  for (size_t k = 0; k < 2; ++k) {
    EXPECT_EQ(read->views()[k].id, views[k].id);
    EXPECT_EQ(read->views()[k].inside, views[k].inside);
    const CameraParameters got = read->views()[k].camera.parameters(), want = views[k].camera.parameters();
    EXPECT_EQ(got.width, want.width);
    EXPECT_NEAR(got.fx, want.fx, 1e-9);
    EXPECT_NEAR(got.cx, want.cx, 1e-9);
    EXPECT_NEAR((got.position - want.position).norm(), 0, 1e-9);
    EXPECT_NEAR((got.rotation - want.rotation).norm(), 0, 1e-9);
  }
  // A mask of another size than its camera's, and a camera without its mask, are named on reading.
  std::vector<Silhouette> smaller = views;
  smaller[1].camera = views[1].camera.Resized(32, 32);
  smaller[1].inside.assign(32 * 32, 1);
  ASSERT_TRUE(VisualHull::Write(root + "/smaller", smaller).ok());
  std::filesystem::copy_file(root + "/smaller/mv-02.png", root + "/silhouette/mv-02.png",
                             std::filesystem::copy_options::overwrite_existing);
  EXPECT_THAT(std::string(VisualHull::Read(root + "/silhouette").status().message()),
              HasSubstr("silhouette/mv-02.png: 32x32"));
  std::filesystem::remove(root + "/silhouette/mv-02.png");
  EXPECT_THAT(std::string(VisualHull::Read(root + "/silhouette").status().message()),
              HasSubstr("silhouette/mv-02.png"));
  // A mask that does not fit its camera is refused on writing.
  smaller[1].inside.assign(16, 1);
  EXPECT_THAT(std::string(VisualHull::Write(root + "/other", smaller).message()), HasSubstr("\"mv-02\""));
}

}  // namespace
}  // namespace stage::processing
