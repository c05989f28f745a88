// MeshBvh: rays aimed exactly at the edges and corners a closed mesh's triangles share still meet it (no shadow ray
// slips into a closed head); hits carry the triangle and barycentrics that give the point back; the segment's ends
// are kept out of Occluded; many segments at once get Occluded's answers; copies outlive the original; an empty mesh
// is hit by nothing.
#include <Eigen/Geometry>
#include <cmath>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "stage/common/mesh.h"

namespace stage {
namespace {

// An axis-aligned cube of side 2 centred at the origin, two triangles a face (each face's diagonal an inner edge).
TriangleMesh Cube() {
  TriangleMesh m;
  for (int i = 0; i < 8; ++i) m.positions.emplace_back(i & 1 ? 1 : -1, i & 2 ? 1 : -1, i & 4 ? 1 : -1);
  const int faces[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& f : faces) {
    m.triangles.push_back({f[0], f[1], f[2]});
    m.triangles.push_back({f[0], f[2], f[3]});
  }
  return m;
}

TEST(MeshBvhTest, RaysThroughSharedEdgesAndCornersDoNotSlipThrough) {
  const MeshBvh bvh(Cube());
  // From outside towards points on every edge and corner of the top face (z = 1), its diagonal included, and from
  // inside the cube out through them: every one meets the cube.
  for (int i = 0; i <= 8; ++i) {
    const float s = -1 + i * 0.25f;
    for (const Eigen::Vector3f& target :
         {Eigen::Vector3f(s, -1, 1), Eigen::Vector3f(s, 1, 1), Eigen::Vector3f(-1, s, 1), Eigen::Vector3f(1, s, 1),
          Eigen::Vector3f(s, s, 1), Eigen::Vector3f(s, -s, 1)}) {
      for (const Eigen::Vector3f& origin : {Eigen::Vector3f(0.3f, 0.2f, 5), Eigen::Vector3f(0.1f, -0.2f, 0)}) {
        const Eigen::Vector3f d = (target - origin).normalized();
        MeshHit hit;
        ASSERT_TRUE(bvh.Nearest(origin, d, INFINITY, &hit))
            << "from " << origin.transpose() << " to " << target.transpose();
        EXPECT_NEAR(hit.t, (target - origin).norm(), 1e-4f);
        EXPECT_TRUE(bvh.Occluded(origin, target + d)) << target.transpose();
      }
    }
  }
}

TEST(MeshBvhTest, HitsGiveThePointBackAndOccludedKeepsTheSegmentsEndsOut) {
  const TriangleMesh cube = Cube();
  const MeshBvh bvh(cube);
  const Eigen::Vector3f origin(0.2f, 0.35f, 4), d(0, 0, -1);
  MeshHit hit;
  ASSERT_TRUE(bvh.Nearest(origin, d, INFINITY, &hit));
  ASSERT_GE(hit.triangle, 0);
  const auto& t = cube.triangles[static_cast<size_t>(hit.triangle)];
  const Eigen::Vector3f p =
      (1 - hit.b1 - hit.b2) * cube.positions[t[0]] + hit.b1 * cube.positions[t[1]] + hit.b2 * cube.positions[t[2]];
  EXPECT_LT((p - (origin + hit.t * d)).norm(), 1e-5f);
  EXPECT_NEAR(p.z(), 1, 1e-6f);
  // Short of the surface: no hit within tmax, nothing between.
  EXPECT_FALSE(bvh.Nearest(origin, d, 2.9f, &hit));
  EXPECT_FALSE(bvh.Occluded(origin, origin + 2.9f * d));
  // A shadow ray leaving the surface (lifted as the renderer lifts it) is not stopped by the surface it leaves.
  EXPECT_FALSE(bvh.Occluded({0.2f, 0.35f, 1.001f}, {0.2f, 0.35f, 100}));
  EXPECT_TRUE(bvh.Occluded({0.2f, 0.35f, 1.001f}, {0.2f, 0.35f, -100}));
  // A segment of no length holds nothing.
  EXPECT_FALSE(bvh.Occluded(origin, origin));
}

TEST(MeshBvhTest, ManySegmentsAtOnceGetOccludedsAnswers) {
  const MeshBvh bvh(Cube());
  std::vector<Eigen::Vector3f> from, to;
  // Through the top face's edges, corners and diagonals from outside (blocked, as above): from one start fanning out,
  // then from many starts towards one end below the cube (the renderer's order: neighbouring points towards one
  // light); then random segments about the cube, some blocked, some not.
  for (int i = 0; i <= 8; ++i) {
    const float s = -1 + i * 0.25f;
    for (const Eigen::Vector3f& target : {Eigen::Vector3f(s, -1, 1), Eigen::Vector3f(s, s, 1)}) {
      const Eigen::Vector3f origin(0.3f, 0.2f, 5);
      from.push_back(origin);
      to.push_back(target + (target - origin).normalized());
    }
  }
  const Eigen::Vector3f end(0.1f, -0.2f, -5);
  for (int i = 0; i <= 8; ++i) {
    const float s = -1 + i * 0.25f;
    for (const Eigen::Vector3f& target : {Eigen::Vector3f(s, 1, 1), Eigen::Vector3f(-s, s, 1)}) {
      from.push_back(target + 3 * (target - end).normalized());
      to.push_back(end);
    }
  }
  const size_t through_edges = from.size();
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-3, 3);
  for (int i = 0; i < 2000; ++i) {
    from.emplace_back(u(rng), u(rng), u(rng));
    to.emplace_back(u(rng), u(rng), u(rng));
  }
  from.emplace_back(0, 0, 5);  // too short to trace: not blocked
  to.emplace_back(0, 0, 5);
  std::vector<uint8_t> blocked(from.size(), 7);
  bvh.Occluded(from, to, blocked);
  int count = 0;
  for (size_t i = 0; i < from.size(); ++i) {
    ASSERT_EQ(blocked[i] != 0, bvh.Occluded(from[i], to[i])) << "segment " << i;
    ASSERT_LE(blocked[i], 1);
    if (i < through_edges) {
      EXPECT_EQ(blocked[i], 1) << "through the edge, segment " << i;
    }
    count += blocked[i];
  }
  EXPECT_EQ(blocked.back(), 0);
  EXPECT_GT(count, 200);  // both answers are exercised
  EXPECT_LT(count, 1800);
  bvh.Occluded(std::span<const Eigen::Vector3f>{}, std::span<const Eigen::Vector3f>{}, std::span<uint8_t>{});
}

TEST(MeshBvhTest, CopiesOutliveTheOriginalAndAnEmptyMeshIsHitByNothing) {
  auto original = std::make_unique<MeshBvh>(Cube());
  const MeshBvh copy = *original;
  original.reset();
  MeshHit hit;
  EXPECT_TRUE(copy.Nearest({0, 0, 5}, {0, 0, -1}, INFINITY, &hit));
  EXPECT_EQ(copy.mesh().triangles.size(), 12u);

  const MeshBvh empty{TriangleMesh{}};
  EXPECT_FALSE(empty.Nearest({0, 0, 5}, {0, 0, -1}, INFINITY, &hit));
  EXPECT_FALSE(empty.Occluded({0, 0, 5}, {0, 0, -5}));
}

}  // namespace
}  // namespace stage
