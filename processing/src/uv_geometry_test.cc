#include "stage/processing/uv_geometry.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>

namespace stage::processing {
namespace {

constexpr float kPi = 3.14159265358979f;

// A sphere of radius `r` (mm) about `centre`, its texture coordinates its longitude (u) and latitude (v) as the
// simulator's head lays out its skin: a (cols + 1) x (rows + 1) grid whose seam column repeats the first at u = 1.
TriangleMesh UvSphere(float r, const Eigen::Vector3f& centre, int cols, int rows) {
  TriangleMesh m;
  for (int j = 0; j <= rows; ++j) {
    const float v = static_cast<float>(j) / rows, lat = v * kPi - kPi / 2;
    for (int i = 0; i <= cols; ++i) {
      const float u = static_cast<float>(i) / cols, lon = u * 2 * kPi - kPi;
      m.positions.push_back(
          centre + r * Eigen::Vector3f(std::sin(lon) * std::cos(lat), std::sin(lat), std::cos(lon) * std::cos(lat)));
      m.uvs.emplace_back(u, v);
    }
  }
  auto at = [&](int i, int j) { return static_cast<int32_t>(j * (cols + 1) + i); };
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      m.triangles.push_back({at(i, j), at(i, j + 1), at(i + 1, j)});
      m.triangles.push_back({at(i + 1, j), at(i, j + 1), at(i + 1, j + 1)});
    }
  }
  return m;
}

TEST(GeometryMapTest, ASpheresMapLiesOnItInTheHeadFrameAndComesBackWhereItWas) {
  const Eigen::Vector3f centre(20, 1500, -40);
  const TriangleMesh sphere = UvSphere(100, centre, 128, 64);
  // The head frame: the sphere's centre at the origin.
  const Eigen::Isometry3f head_from_stage(Eigen::Translation3f(-centre));
  auto map = MakeGeometryMap(sphere, head_from_stage, {.size = 256, .dilation_px = 0});
  ASSERT_TRUE(map.ok()) << map.status();
  // The grid covers the whole square: no texel empty, none dilated.
  EXPECT_EQ(map->Count(TexelState::kCovered), 256 * 256);
  // Every point lies between the facets' nearest approach to the centre and the sphere: the chord's sagitta of a
  // 2.8 degree cell is 0.03 % of the radius (0.03 mm), 0.06 mm across its diagonal.
  for (int64_t i = 0; i < 256 * 256; i += 7) {
    const float d = map->points[static_cast<size_t>(i)].norm();
    ASSERT_LE(d, 100.0f + 1e-3f) << i;
    ASSERT_GE(d, 99.9f) << i;
  }
  const RoundTripError e = MeasureRoundTrip(sphere, head_from_stage, *map);
  EXPECT_EQ(e.missed, 0);
  EXPECT_EQ(e.samples, static_cast<int64_t>(sphere.triangles.size() + sphere.positions.size()));
  // Bilinear sampling of a 2.5 x 1.2 mm texel grid against the mesh's own 4.9 x 4.9 mm facets: 0.013 mm mean, 0.05
  // at the 99th percentile (measured).
  EXPECT_LT(e.mean_mm, 0.02);
  EXPECT_LT(e.p99_mm, 0.08);
  std::printf("sphere at 256: mean %.4f, p99 %.4f, worst %.4f mm\n", e.mean_mm, e.p99_mm, e.max_mm);
  // Half the resolution: the error grows (it is measured, not assumed).
  auto coarse = MakeGeometryMap(sphere, head_from_stage, {.size = 32, .dilation_px = 0});
  ASSERT_TRUE(coarse.ok());
  EXPECT_GT(MeasureRoundTrip(sphere, head_from_stage, *coarse).mean_mm, 4 * e.mean_mm);
}

TEST(GeometryMapTest, DilationGrowsPastTheLayoutsEdgeByItsRingsAndNoFurther) {
  // A patch of the sphere's layout: the front quarter only, so the rest of the square is empty.
  TriangleMesh sphere = UvSphere(100, Eigen::Vector3f::Zero(), 64, 32);
  TriangleMesh patch = sphere;
  patch.triangles.clear();
  for (const auto& t : sphere.triangles) {
    const Eigen::Vector2f c = (sphere.uvs[t[0]] + sphere.uvs[t[1]] + sphere.uvs[t[2]]) / 3;
    if (c.x() > 0.375f && c.x() < 0.625f && c.y() > 0.25f && c.y() < 0.75f) patch.triangles.push_back(t);
  }
  auto bare = MakeGeometryMap(patch, Eigen::Isometry3f::Identity(), {.size = 64, .dilation_px = 0});
  auto grown = MakeGeometryMap(patch, Eigen::Isometry3f::Identity(), {.size = 64, .dilation_px = 3});
  ASSERT_TRUE(bare.ok() && grown.ok());
  EXPECT_EQ(bare->Count(TexelState::kDilated), 0);
  EXPECT_EQ(grown->Count(TexelState::kCovered), bare->Count(TexelState::kCovered));
  // The covered block is 16 x 32 texels; three rings about it make it 22 x 38.
  EXPECT_EQ(bare->Count(TexelState::kCovered), 16 * 32);
  EXPECT_EQ(grown->Count(TexelState::kDilated), 22 * 38 - 16 * 32);
  // Grown points continue the surface along its slope (its tangent): a point d from the edge leaves the sphere by
  // about d^2 / 2R, the third ring by up to 6 mm; a flat copy of the edge would stay on the sphere's edge.
  auto ring1 = MakeGeometryMap(patch, Eigen::Isometry3f::Identity(), {.size = 64, .dilation_px = 1});
  ASSERT_TRUE(ring1.ok());
  for (size_t i = 0; i < grown->state.size(); ++i) {
    if (grown->state[i] == TexelState::kEmpty) {
      EXPECT_TRUE(std::isnan(grown->points[i].x()));
    } else {
      EXPECT_NEAR(grown->points[i].norm(), 100, 6.5) << i;
    }
    if (ring1->state[i] == TexelState::kDilated) {
      // d = 4.9 to 11 mm (a texel is 9.8 x 4.9 mm): 0.1 to 0.6 mm out, up to 1 where the edge turns a corner.
      EXPECT_GT(ring1->points[i].norm(), 100.1f) << i;
      EXPECT_LT(ring1->points[i].norm(), 101.0f) << i;
    }
  }
  // A sample near the patch's edge reads the dilated ring instead of failing; one far outside fails.
  EXPECT_FALSE(SampleGeometryMap(*bare, {0.376f, 0.5f}).has_value());
  EXPECT_TRUE(SampleGeometryMap(*grown, {0.376f, 0.5f}).has_value());
  EXPECT_FALSE(SampleGeometryMap(*grown, {0.1f, 0.5f}).has_value());
}

TEST(GeometryMapTest, TheFileHoldsThePointsAndTheirStatesExactly) {
  const TriangleMesh sphere = UvSphere(90, Eigen::Vector3f(0, 1400, 0), 32, 16);
  TriangleMesh half = sphere;
  half.triangles.resize(sphere.triangles.size() / 2);
  auto map = MakeGeometryMap(half, Eigen::Isometry3f::Identity(), {.size = 48, .dilation_px = 2});
  ASSERT_TRUE(map.ok());
  ASSERT_GT(map->Count(TexelState::kEmpty), 0);
  ASSERT_GT(map->Count(TexelState::kDilated), 0);
  const std::string path = ::testing::TempDir() + "/geometry_map.exr";
  ASSERT_TRUE(WriteGeometryMap(path, *map).ok());
  auto back = ReadGeometryMap(path);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->size, 48);
  for (size_t i = 0; i < map->state.size(); ++i) {
    ASSERT_EQ(back->state[i], map->state[i]) << i;
    if (map->state[i] != TexelState::kEmpty) {
      ASSERT_EQ(back->points[i], map->points[i]) << i;
    }
  }
}

TEST(GeometryMapTest, BadInputIsRefusedSayingWhat) {
  TriangleMesh no_uvs = UvSphere(50, Eigen::Vector3f::Zero(), 8, 4);
  no_uvs.uvs.clear();
  auto a = MakeGeometryMap(no_uvs, Eigen::Isometry3f::Identity(), {});
  EXPECT_EQ(a.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(a.status().message().find("texture coordinates"), std::string::npos) << a.status();
  auto b = MakeGeometryMap(UvSphere(50, Eigen::Vector3f::Zero(), 8, 4), Eigen::Isometry3f::Identity(), {.size = 8});
  EXPECT_NE(b.status().message().find("size 8"), std::string::npos) << b.status();
  EXPECT_FALSE(GeometryMapOptions{.dilation_px = -1}.Validate().ok());
  EXPECT_EQ(ReadGeometryMap(::testing::TempDir() + "/missing.exr").status().code(), absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace stage::processing
