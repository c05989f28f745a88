// The expression VAE on made-up crops: each frame's expression is a bright blob (its place and size two signals of
// the frame), each camera's view the background's shading. Training on triplets lowers its losses, and the latents
// come apart: a frame's expression latent with another camera's view latent decodes to that frame seen by that
// camera.
#include "stage/processing/asset_net.h"

#include <cmath>
#include <cstdlib>
#include <iostream>
#include <random>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::processing {
namespace {

constexpr int kSize = 32;

std::vector<float> Crop(int frame, int view) {
  const float cx = 16 + 7 * std::sin(0.37f * frame), radius = 3.5f + 2 * std::cos(0.23f * frame);
  std::vector<float> image(kSize * kSize);
  for (int y = 0; y < kSize; ++y) {
    for (int x = 0; x < kSize; ++x) {
      const float u = (x + 0.5f) / kSize, v = (y + 0.5f) / kSize;
      const float background = view == 0 ? 0.1f + 0.3f * u : view == 1 ? 0.1f + 0.3f * v : 0.4f - 0.3f * u;
      const float d2 = (x - cx) * (x - cx) + (y - 16.f) * (y - 16.f);
      image[y * kSize + x] = background + 0.5f * std::exp(-d2 / (radius * radius));
    }
  }
  return image;
}

double Distance(const std::vector<float>& a, const std::vector<float>& b) {
  double d = 0;
  for (size_t i = 0; i < a.size(); ++i) d += (a[i] - b[i]) * (a[i] - b[i]);
  return std::sqrt(d / static_cast<double>(a.size()));
}

TEST(ExpressionVaeTest, TrainingOnTripletsLowersTheLossesAndSeparatesExpressionFromView) {
  ExpressionVaeOptions options{.input_size = kSize,
                               .levels = 3,
                               .base_channels = 8,
                               .max_channels = 32,
                               .expression_latent = 4,
                               .view_latent = 2,
                               .threads = 1,
                               .seed = 5};
  auto net = ExpressionVae::Create(options);
  ASSERT_TRUE(net.ok()) << net.status();
  std::mt19937 rng(11);
  std::normal_distribution<float> normal;
  constexpr int kFrames = 40, kBatch = 8, kSteps = 400;
  std::vector<double> totals;
  for (int step = 0; step < kSteps; ++step) {
    ExpressionBatch batch;
    batch.batch = kBatch;
    for (int k = 0; k < kBatch; ++k) {
      const int a = static_cast<int>(rng() % kFrames), b = static_cast<int>(rng() % kFrames);
      const int i = static_cast<int>(rng() % 3), j = (i + 1 + static_cast<int>(rng() % 2)) % 3;
      for (auto [image, out] : {std::pair{Crop(a, i), &batch.anchor}, std::pair{Crop(a, j), &batch.same_expression},
                                std::pair{Crop(b, i), &batch.same_view}}) {
        out->insert(out->end(), image.begin(), image.end());
      }
    }
    for (int n = 0; n < 3 * kBatch * 6; ++n) batch.noise.push_back(normal(rng));
    auto losses = (*net)->TrainStep(batch, step < 300 ? 3e-3 : 6e-4);
    ASSERT_TRUE(losses.ok()) << losses.status();
    totals.push_back(losses->total);
  }
  double first = 0, last = 0;
  for (int k = 0; k < 20; ++k) first += totals[k] / 20, last += totals[kSteps - 20 + k] / 20;
  EXPECT_LT(last, 0.3 * first) << "first " << first << ", last " << last;

  // Frame 7 seen by camera 0, frame 23 seen by camera 2: frame 7's expression with camera 2's view decodes to frame 7
  // seen by camera 2, closer to it than to either input.
  std::vector<float> pair = Crop(7, 0);
  const std::vector<float> other = Crop(23, 2);
  pair.insert(pair.end(), other.begin(), other.end());
  auto latents = (*net)->Encode(pair, 2);
  ASSERT_TRUE(latents.ok());
  std::vector<float> mixed(latents->begin(), latents->begin() + 4);            // frame 7's expression
  mixed.insert(mixed.end(), latents->begin() + 6 + 4, latents->begin() + 12);  // camera 2's view
  auto decoded = (*net)->Decode(mixed, 1);
  ASSERT_TRUE(decoded.ok());
  const double to_target = Distance(*decoded, Crop(7, 2));
  EXPECT_LT(to_target, 0.6 * Distance(*decoded, Crop(7, 0))) << to_target;
  EXPECT_LT(to_target, 0.6 * Distance(*decoded, Crop(23, 2))) << to_target;

  EXPECT_THAT((*net)->Encode({1.f, 2.f}, 1).status().message(),
              ::testing::HasSubstr("expression VAE: the images holds 2 values"));
}

// The driving path's map loss: the driven and the target latents decoded by the geometry VAE's decoder, compared
// texel by texel as the weights say; a geometry VAE of another latent and weights of another size are refused.
TEST(DrivingNetTest, TheMapLossComparesTheDecodedMapsWhereTheWeightsSay) {
  auto expression = ExpressionVae::Create(
      {.input_size = kSize, .levels = 3, .max_channels = 32, .expression_latent = 4, .view_latent = 2, .threads = 1});
  ASSERT_TRUE(expression.ok()) << expression.status();
  auto mapping = LatentMapping::Create({.input = 4, .output = 3, .hidden = 16, .layers = 2, .threads = 1},
                                       std::vector<float>(3, 0.f), std::vector<float>(3, 1.f));
  ASSERT_TRUE(mapping.ok()) << mapping.status();
  const GeometryVaeOptions g{
      .input_size = 32, .levels = 3, .max_channels = 16, .geometry_latent = 3, .pose_latent = 2, .threads = 1};
  auto geometry = GeometryVae::Create(g, std::vector<float>(3 * 32 * 32, 0.f), 1.f);
  ASSERT_TRUE(geometry.ok()) << geometry.status();
  std::vector<float> images = Crop(3, 0);
  const std::vector<float> second = Crop(9, 1);
  images.insert(images.end(), second.begin(), second.end());
  auto make = [&] { return DrivingNet::Create(**expression, **mapping, {.threads = 1}); };
  auto latent = make(), map = make(), nowhere = make();
  ASSERT_TRUE(latent.ok() && map.ok() && nowhere.ok());
  auto driven = (*latent)->Drive(images, 2);
  ASSERT_TRUE(driven.ok()) << driven.status();
  std::vector<float> moved = *driven;
  moved[1] += 2;  // the first crop's target, one latent number off

  EXPECT_THAT(std::string((*map)->UseMapLoss(**geometry, std::vector<float>(31 * 31, 1.f)).message()),
              ::testing::HasSubstr("the texels' weights holds 961 values"));
  auto other = GeometryVae::Create({.input_size = 32, .levels = 3, .max_channels = 16, .geometry_latent = 5},
                                   std::vector<float>(3 * 32 * 32, 0.f), 1.f);
  ASSERT_TRUE(other.ok());
  EXPECT_THAT(std::string((*map)->UseMapLoss(**other, std::vector<float>(32 * 32, 1.f)).message()),
              ::testing::HasSubstr("the geometry VAE's latent has 5 numbers, the mapping gives 3"));
  ASSERT_TRUE((*map)->UseMapLoss(**geometry, std::vector<float>(32 * 32, 1.f)).ok());
  ASSERT_TRUE((*nowhere)->UseMapLoss(**geometry, std::vector<float>(32 * 32, 0.f)).ok());

  // A step at a negligible rate reads the loss without moving the nets. On its own targets each loss is 0; one
  // latent number off, the latent loss and the map loss see it, weights of 0 everywhere do not.
  constexpr double kRate = 1e-12;
  for (auto* net : {&*latent, &*map, &*nowhere}) {
    auto same = (*net)->TrainStep(images, *driven, 2, kRate);
    ASSERT_TRUE(same.ok()) << same.status();
    EXPECT_NEAR(*same, 0, 1e-9);
  }
  auto latent_off = (*latent)->TrainStep(images, moved, 2, kRate);
  auto map_off = (*map)->TrainStep(images, moved, 2, kRate);
  auto nowhere_off = (*nowhere)->TrainStep(images, moved, 2, kRate);
  ASSERT_TRUE(latent_off.ok() && map_off.ok() && nowhere_off.ok());
  EXPECT_GT(*latent_off, 0.1);
  EXPECT_GT(*map_off, 1e-6);
  EXPECT_NE(*map_off, *latent_off);
  EXPECT_EQ(*nowhere_off, 0);
}

// The nets live in a module that a process opens the first time it makes one (torch_nets.h). Without it, making a net
// is an error that names the file, not a crash at the process's start. In a fresh process (the threadsafe death test
// runs this test alone in a new one): the module is opened once per process.
TEST(TorchNetsDeathTest, AMissingModuleIsAnErrorThatNamesIt) {
  GTEST_FLAG_SET(death_test_style, "threadsafe");
  EXPECT_EXIT(
      {
        setenv("FASTAGE_TORCH_NETS", "/nonexistent/libstage_torch_nets.so", 1);
        auto net = ExpressionVae::Create({.input_size = kSize, .levels = 2});
        std::cerr << net.status() << "\n";
        std::exit(net.ok() ? 1 : 0);
      },
      ::testing::ExitedWithCode(0), "FAILED_PRECONDITION.*/nonexistent/libstage_torch_nets.so: no such file");
}

}  // namespace
}  // namespace stage::processing
