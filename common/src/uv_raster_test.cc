#include "stage/common/uv_raster.h"

#include <gtest/gtest.h>

namespace stage {
namespace {

// A square of side 1 in the z = 0 plane whose texture coordinates are its x, y.
TriangleMesh UnitSquare() {
  TriangleMesh m;
  m.positions = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}};
  for (const auto& p : m.positions) m.uvs.emplace_back(p.x(), p.y());
  m.triangles = {{{0, 1, 2}}, {{0, 2, 3}}};
  return m;
}

TEST(UvRasterTest, EveryTexelOfASquareIsCoveredAndRowZeroIsTheTopOfTheLayout) {
  const TriangleMesh square = UnitSquare();
  const int size = 16;
  const std::vector<UvTexel> texels = RasterizeUv(square, size);
  const std::vector<Eigen::Vector3f> points =
      InterpolateAtTexels(square, texels, square.positions, Eigen::Vector3f::Constant(-1));
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const size_t i = static_cast<size_t>(y) * size + x;
      ASSERT_TRUE(texels[i].covered()) << x << "," << y;
      const Eigen::Vector2f uv = TexelUv(x, y, size);
      EXPECT_NEAR(points[i].x(), uv.x(), 1e-5);
      EXPECT_NEAR(points[i].y(), uv.y(), 1e-5);
    }
  }
  // Texel (0, 0) is the top-left: u small, v near 1.
  EXPECT_NEAR(points[0].y(), 1 - 0.5 / size, 1e-5);
}

TEST(UvRasterTest, OnlyThePartAskedForIsDrawnAndUncoveredTexelsGetTheEmptyValue) {
  TriangleMesh square = UnitSquare();
  square.parts = {0, 1};  // the lower-right triangle skin, the upper-left an eye
  const int size = 32;
  const std::vector<UvTexel> texels = RasterizeUv(square, size, /*part=*/0);
  const std::vector<Eigen::Vector3f> points =
      InterpolateAtTexels(square, texels, square.positions, Eigen::Vector3f::Constant(-1));
  int covered = 0;
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const size_t i = static_cast<size_t>(y) * size + x;
      const Eigen::Vector2f uv = TexelUv(x, y, size);
      if (uv.x() > uv.y() + 1e-3f) {
        EXPECT_TRUE(texels[i].covered());
        ++covered;
      } else if (uv.x() < uv.y() - 1e-3f) {
        EXPECT_FALSE(texels[i].covered());
        EXPECT_EQ(points[i], Eigen::Vector3f::Constant(-1));
      }
    }
  }
  EXPECT_EQ(covered, size * (size - 1) / 2);
  // Every part.
  int all = 0;
  for (const UvTexel& t : RasterizeUv(square, size, /*part=*/-1)) all += t.covered() ? 1 : 0;
  EXPECT_EQ(all, size * size);
}

TEST(UvRasterTest, AMeshWithoutTextureCoordinatesCoversNothing) {
  TriangleMesh square = UnitSquare();
  square.uvs.clear();
  for (const UvTexel& t : RasterizeUv(square, 8)) EXPECT_FALSE(t.covered());
}

}  // namespace
}  // namespace stage
