// The driven textures at full resolution (asset_train_internal.h's ApplyWrinkleMaps): the neutral frame's textures
// with the decoded wrinkle maps upsampled onto them, texel centres aligned.
#include <Eigen/Core>
#include <cmath>

#include "asset_train_internal.h"
#include "gtest/gtest.h"

namespace stage::processing::asset_internal {
namespace {

constexpr int kNet = 4, kFull = 16;

// Neutral textures of fine detail (a checker per texel) at kFull, valid but for the top-left 2 x 2 texels; their
// net-size version some other values (the wrinkle is what the decoded textures add to those), all valid.
NeutralTextures MakeNeutral() {
  NeutralTextures n;
  n.albedo = Image(kFull, kFull, 4);
  n.specular = Image(kFull, kFull, 1);
  n.normal = Image(kFull, kFull, 3);
  for (int y = 0; y < kFull; ++y) {
    for (int x = 0; x < kFull; ++x) {
      const float checker = (x + y) % 2 ? 0.1f : 0.f;
      float* a = n.albedo.at(x, y);
      a[0] = 0.3f + checker, a[1] = 0.4f, a[2] = 0.2f + checker;
      a[3] = x < 2 && y < 2 ? 0.f : 1.f;
      n.specular.at(x, y)[0] = 0.05f + checker / 10;
      const Eigen::Vector3f normal = Eigen::Vector3f(checker, -checker, 1).normalized();
      std::copy(normal.data(), normal.data() + 3, n.normal.at(x, y));
    }
  }
  n.net_size = kNet;
  n.net.resize(kTextureChannels * kNet * kNet);
  for (size_t i = 0; i < n.net.size(); ++i) n.net[i] = 0.1f + 0.01f * static_cast<float>(i % 17);
  n.net_valid.assign(kNet * kNet, 1.f);
  return n;
}

TEST(WrinkleMapTest, WithoutWrinklesTheDrivenTexturesAreTheNeutralFrameAtFullResolution) {
  const NeutralTextures neutral = MakeNeutral();
  const TextureImages t = ApplyWrinkleMaps(neutral, neutral.net);
  ASSERT_EQ(t.albedo.width, kFull);
  ASSERT_EQ(t.albedo.channels, 3);
  for (int y = 0; y < kFull; ++y) {
    for (int x = 0; x < kFull; ++x) {
      const bool valid = neutral.albedo.at(x, y)[3] == 1;
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(t.albedo.at(x, y)[c], valid ? neutral.albedo.at(x, y)[c] : 0.f) << x << ", " << y;
        EXPECT_NEAR(t.normal.at(x, y)[c], valid ? neutral.normal.at(x, y)[c] : 0.f, 1e-6) << x << ", " << y;
      }
      EXPECT_EQ(t.specular.at(x, y)[0], valid ? neutral.specular.at(x, y)[0] : 0.f);
    }
  }
}

// A wrinkle that rises linearly along u at the net's size comes back linear at full size, with the texel centres of
// both sizes in their places ((x + 0.5) / 16 of the way across is (x + 0.5) / 4 texels of the net's), flat past the
// outermost centres; a constant one is added as it is; albedo never goes below 0; and a net texel without the skin
// adds nothing.
TEST(WrinkleMapTest, TheWrinkleMapsAreUpsampledBilinearlyWithTexelCentresAligned) {
  NeutralTextures neutral = MakeNeutral();
  std::vector<float> decoded = neutral.net;
  const int texels = kNet * kNet;
  for (int y = 0; y < kNet; ++y) {
    for (int x = 0; x < kNet; ++x) {
      decoded[0 * texels + y * kNet + x] += 0.02f * x;  // albedo R: a ramp along u
      decoded[1 * texels + y * kNet + x] -= 1.f;        // albedo G: below 0 everywhere
      decoded[3 * texels + y * kNet + x] += 0.01f;      // specular: a constant
    }
  }
  const TextureImages t = ApplyWrinkleMaps(neutral, decoded);
  for (int y = 2; y < kFull; ++y) {
    for (int x = 0; x < kFull; ++x) {
      const double at_net = std::clamp((x + 0.5) * kNet / kFull - 0.5, 0.0, kNet - 1.0);
      EXPECT_NEAR(t.albedo.at(x, y)[0] - neutral.albedo.at(x, y)[0], 0.02 * at_net, 1e-6) << x << ", " << y;
      EXPECT_EQ(t.albedo.at(x, y)[1], 0.f);
      EXPECT_NEAR(t.specular.at(x, y)[0] - neutral.specular.at(x, y)[0], 0.01, 1e-6);
      EXPECT_NEAR(Eigen::Map<const Eigen::Vector3f>(t.normal.at(x, y)).norm(), 1, 1e-6);
    }
  }
  // The last net texel without the skin: its wrinkle is not taken (the full texels nearest it keep the neutral's).
  neutral.net_valid[texels - 1] = 0;
  const TextureImages cut = ApplyWrinkleMaps(neutral, decoded);
  EXPECT_NEAR(cut.specular.at(kFull - 1, kFull - 1)[0], neutral.specular.at(kFull - 1, kFull - 1)[0], 1e-6);
  EXPECT_NEAR(cut.specular.at(0, kFull - 1)[0] - neutral.specular.at(0, kFull - 1)[0], 0.01, 1e-6);
}

}  // namespace
}  // namespace stage::processing::asset_internal
