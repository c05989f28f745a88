#include "stage/processing/stabilize.h"

#include <cmath>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

// Textures whose albedo is a skin-like pattern (blotches and pores) moved by (dx, dy) texels; every texel covered.
FusedTextures Pattern(int size, float dx, float dy) {
  FusedTextures t;
  t.size = size;
  t.albedo = Image(size, size, 3);
  t.normal_object = Image(size, size, 3);
  t.weight = Image(size, size, 1);
  t.state.assign(static_cast<size_t>(size) * size, TexelState::kCovered);
  t.views.assign(t.state.size(), 1);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const float u = static_cast<float>(x) - dx, v = static_cast<float>(y) - dy;
      const float l = 0.5f + 0.1f * std::sin(0.21f * u) * std::cos(0.17f * v) + 0.05f * std::sin(0.35f * u + 0.5f * v) +
                      0.04f * std::cos(0.45f * u - 0.3f * v);
      float* a = t.albedo.at(x, y);
      a[0] = l;
      a[1] = 0.8f * l;
      a[2] = 0.6f * l;
      float* n = t.normal_object.at(x, y);
      n[2] = 1;
      t.weight.at(x, y)[0] = 1;
    }
  }
  return t;
}

TEST(StabilizeTest, ATextureMovedAlongTheLayoutIsMovedBack) {
  const FusedTextures reference = Pattern(128, 0, 0), moved = Pattern(128, 2.5f, -1.5f);
  auto s = StabilizeTextures(reference, moved, {});
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_NEAR(s->mean_flow_px, std::hypot(2.5, 1.5), 0.3);
  // Inside (what moved in across the border has no source).
  std::vector<bool> inside(128 * 128, false);
  for (int y = 8; y < 120; ++y) {
    for (int x = 8; x < 120; ++x) inside[static_cast<size_t>(y) * 128 + x] = true;
  }
  const double before = AlbedoJitter(reference, moved, &inside), after = AlbedoJitter(reference, s->textures, &inside);
  EXPECT_GT(before, 0.05);
  EXPECT_LT(after, before / 10);
  // Away from the border the flow is the move.
  const float* f = s->flow.at(64, 64);
  EXPECT_NEAR(f[0], 2.5, 0.2);
  EXPECT_NEAR(f[1], -1.5, 0.2);
  // The normals follow, unit length.
  const float* n = s->textures.normal_object.at(64, 64);
  EXPECT_NEAR(std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), 1, 1e-5);
}

TEST(StabilizeTest, RefusesBadOptionsAndTexturesOfAnotherSize) {
  StabilizeOptions o;
  o.patch_stride = 20;
  EXPECT_THAT(std::string(o.Validate().message()), HasSubstr("patch_stride 20"));
  o = {};
  o.max_flow_px = 0;
  EXPECT_THAT(std::string(StabilizeTextures(Pattern(32, 0, 0), Pattern(32, 0, 0), o).status().message()),
              HasSubstr("max_flow_px"));
  EXPECT_THAT(std::string(StabilizeTextures(Pattern(32, 0, 0), Pattern(64, 0, 0), {}).status().message()),
              HasSubstr("64 texels across against a reference of 32"));
}

}  // namespace
}  // namespace stage::processing
