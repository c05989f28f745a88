// The neural asset's dataset on a made-up take: a truth whose surface is a known function of the head's layout (so
// the expected geometry is exact), frames named into sequences; the split, the file and the errors.
#include "stage/processing/asset_dataset.h"

#include <Eigen/Geometry>
#include <filesystem>

#include "asset_test_support.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/processing/face_template.h"
#include "stage/processing/photometric_stage.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

// The made-up truth's surface: linear in the head's layout, so bilinear interpolation between texels is exact.
Eigen::Vector3f Surface(const Eigen::Vector2f& uv) { return {200 * uv.x() - 100, 150 * uv.y() - 60, 80 + 30 * uv.x()}; }

std::string MakeTake(const std::string& name, int frames) {
  return asset_testing::MakeTruthTake(name, frames, [](const Eigen::Vector2f& uv, int) { return Surface(uv); });
}

TEST(AssetDatasetTest, TheTruthIsDrawnIntoTheTemplatesLayoutInTheHeadsFrameAndSplit) {
  const std::string take = MakeTake("asset-take", 50);
  DatasetOptions options{.take_dir = take, .geometry_size = 64};
  int64_t calls = 0;
  options.progress = [&](int64_t done, int64_t total) {
    ++calls;
    EXPECT_EQ(total, 50);
  };
  auto summary = BuildAssetDataset(options);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(calls, 50);
  EXPECT_EQ(summary->path, take + "/derived/asset/dataset.h5");
  EXPECT_EQ(summary->frames, 50);
  // Five sequences; the last whole one (seq-3) held out, then 20 % of the other 40 frames in 5 blocks of 2.
  EXPECT_EQ(summary->sequences.size(), 5u);
  EXPECT_EQ(summary->sequence, "seq-3");
  EXPECT_EQ(summary->held_out_sequence, 10);
  EXPECT_EQ(summary->held_out_block, 10);
  EXPECT_EQ(summary->train, 30);

  auto dataset = ReadAssetDataset(summary->path);
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  ASSERT_EQ(dataset->frames(), 50);
  EXPECT_EQ(dataset->geometry_size, 64);
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  int64_t valid = 0;
  double worst = 0;
  for (int64_t i = 0; i < 50; i += 7) {
    EXPECT_EQ(dataset->frame[i], i);
    EXPECT_EQ(dataset->split[i] == SampleSplit::kHeldOutSequence, i >= 30 && i < 40) << i;
    for (int t = 0; t < 64 * 64; ++t) {
      if (!dataset->valid[i * 64 * 64 + t]) continue;
      ++valid;
      // The head frame's point is the surface at the texel's place in the head's layout: the pose is taken out.
      const Eigen::Vector2f uv((t % 64 + 0.5f) / 64, 1 - (t / 64 + 0.5f) / 64);
      const Eigen::Vector3f expected = Surface(face->HeadLayoutUv(uv));
      const Eigen::Vector3f got = Eigen::Map<const Eigen::Vector3f>(&dataset->geometry[(i * 64 * 64 + t) * 3]);
      worst = std::max(worst, static_cast<double>((got - expected).norm()));
    }
    Eigen::Matrix4f pose;
    for (int k = 0; k < 16; ++k) pose(k / 4, k % 4) = dataset->stage_from_head[i * 16 + k];
    EXPECT_TRUE(pose.isApprox(asset_testing::MadeUpPose(i).matrix(), 1e-5f)) << i;
  }
  EXPECT_LT(worst, 1e-3);
  // The template's layout covers most of the square (its face and the dilation past its edges).
  EXPECT_GT(valid, 8 * 64 * 64 / 2);
  EXPECT_GT(summary->rms_from_mean_mm, 0);  // the truth is the same surface every frame, but numbers differ by rounding
  EXPECT_LT(summary->rms_from_mean_mm, 1e-3);

  // Every third frame of 5..49: 5, 8, ..., 47.
  options.first_frame = 5;
  options.frame_step = 3;
  options.output = take + "/every-third.h5";
  options.progress = nullptr;
  auto every_third = BuildAssetDataset(options);
  ASSERT_TRUE(every_third.ok()) << every_third.status();
  auto thinned = ReadAssetDataset(every_third->path);
  ASSERT_TRUE(thinned.ok()) << thinned.status();
  ASSERT_EQ(thinned->frames(), 15);
  for (int64_t i = 0; i < 15; ++i) EXPECT_EQ(thinned->frame[i], 5 + 3 * i);
}

// The truth's textures (uv_albedo, uv_material, uv_normal in the head's frame) drawn into the template's layout, the
// normals in tangent space over the surface: on the made-up plane the tangent frame is known, so a normal tilted
// from it by a known amount must come back as that tilt.
TEST(AssetDatasetTest, TheTruthsTexturesAreDrawnIntoTheLayoutWithTangentSpaceNormals) {
  const std::string take = MakeTake("asset-textures", 3);
  const Eigen::Vector3f du(200, 0, 30), dv(0, 150, 0);  // Surface's slopes along the head layout's u and v
  const Eigen::Vector3f normal = du.cross(dv).normalized(), tangent = du.normalized(),
                        bitangent = normal.cross(tangent);
  const Eigen::Vector3f tilt = Eigen::Vector3f(0.2f, -0.1f, 1).normalized();
  const Eigen::Vector3f detailed = tilt.x() * tangent + tilt.y() * bitangent + tilt.z() * normal;
  auto albedo = [](const Eigen::Vector2f& uv) { return Eigen::Vector3f(0.3f + 0.2f * uv.x(), 0.4f, 0.5f * uv.y()); };
  for (int f = 0; f < 3; ++f) {
    Image a(128, 128, 4), m(128, 128, 4), n(128, 128, 4);
    for (int y = 0; y < 128; ++y) {
      for (int x = 0; x < 128; ++x) {
        const Eigen::Vector3f rgb = albedo({(x + 0.5f) / 128, 1 - (y + 0.5f) / 128});
        std::copy(rgb.data(), rgb.data() + 3, a.at(x, y));
        std::copy(detailed.data(), detailed.data() + 3, n.at(x, y));
        m.at(x, y)[0] = 0.05f;
        a.at(x, y)[3] = m.at(x, y)[3] = n.at(x, y)[3] = 1;
      }
    }
    const std::string dir = FrameDir(take + "/ground_truth", f);
    ASSERT_TRUE(WriteExr(dir + "/uv_albedo.exr", a).ok());
    ASSERT_TRUE(WriteExr(dir + "/uv_material.exr", m).ok());
    ASSERT_TRUE(WriteExr(dir + "/uv_normal.exr", n).ok());
  }
  auto summary = BuildAssetDataset({.take_dir = take, .geometry_size = 32, .texture_size = 48});
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->texture_size, 48);
  auto dataset = ReadAssetDataset(summary->path);
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  ASSERT_EQ(dataset->texture_size, 48);
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  int64_t valid = 0;
  double worst_albedo = 0, worst_angle = 0, worst_specular = 0;
  for (int64_t i = 0; i < 3; ++i) {
    for (int t = 0; t < 48 * 48; ++t) {
      if (!dataset->texture_valid[i * 48 * 48 + t]) continue;
      ++valid;
      const float* got = &dataset->textures[(i * 48 * 48 + t) * kTextureChannels];
      const Eigen::Vector2f uv((t % 48 + 0.5f) / 48, 1 - (t / 48 + 0.5f) / 48);
      worst_albedo = std::max(
          worst_albedo,
          static_cast<double>(
              (Eigen::Vector3f(got[0], got[1], got[2]) - albedo(face->HeadLayoutUv(uv))).cwiseAbs().maxCoeff()));
      worst_specular = std::max(worst_specular, std::abs(got[3] - 0.05));
      const Eigen::Vector3f n(got[4], got[5], got[6]);
      worst_angle = std::max(worst_angle, std::acos(std::clamp<double>(n.dot(tilt), -1, 1)) * 180 / M_PI);
    }
  }
  EXPECT_GT(valid, 3 * 48 * 48 / 2);
  EXPECT_LT(worst_albedo, 1e-4);
  EXPECT_LT(worst_specular, 1e-6);
  EXPECT_LT(worst_angle, 0.05) << "degrees";
  // The neutral (first) frame's textures at full resolution beside the dataset: by default at the truth's own size,
  // drawn as the dataset's are.
  EXPECT_EQ(summary->neutral_texture_size, 128);
  EXPECT_EQ(dataset->neutral_texture_size, 128);
  EXPECT_EQ(dataset->neutral_textures_dir, summary->neutral_textures_dir);
  auto full_albedo = ReadImageFile(dataset->neutral_textures_dir + "/albedo.exr");
  auto full_specular = ReadImageFile(dataset->neutral_textures_dir + "/specular.exr");
  auto full_normal = ReadImageFile(dataset->neutral_textures_dir + "/normal_tangent.exr");
  ASSERT_TRUE(full_albedo.ok() && full_specular.ok() && full_normal.ok()) << full_albedo.status();
  ASSERT_EQ(full_albedo->width, 128);
  ASSERT_EQ(full_albedo->channels, 4);
  int64_t full_valid = 0;
  worst_albedo = worst_angle = worst_specular = 0;
  for (int y = 0; y < 128; ++y) {
    for (int x = 0; x < 128; ++x) {
      if (full_albedo->at(x, y)[3] != 1) continue;
      ++full_valid;
      const float* a = full_albedo->at(x, y);
      const Eigen::Vector2f uv((x + 0.5f) / 128, 1 - (y + 0.5f) / 128);
      worst_albedo =
          std::max(worst_albedo,
                   static_cast<double>(
                       (Eigen::Vector3f(a[0], a[1], a[2]) - albedo(face->HeadLayoutUv(uv))).cwiseAbs().maxCoeff()));
      worst_specular = std::max(worst_specular, std::abs(full_specular->at(x, y)[0] - 0.05));
      const Eigen::Vector3f n(full_normal->at(x, y)[0], full_normal->at(x, y)[1], full_normal->at(x, y)[2]);
      worst_angle = std::max(worst_angle, std::acos(std::clamp<double>(n.dot(tilt), -1, 1)) * 180 / M_PI);
    }
  }
  EXPECT_GT(full_valid, 128 * 128 / 2);
  EXPECT_LT(worst_albedo, 1e-4);
  EXPECT_LT(worst_specular, 1e-6);
  EXPECT_LT(worst_angle, 0.05) << "degrees";
  // At the dataset's own size they are its first frame's textures; -1 keeps none.
  auto same = BuildAssetDataset({.take_dir = take,
                                 .output = take + "/same.h5",
                                 .geometry_size = 32,
                                 .texture_size = 48,
                                 .neutral_texture_size = 48});
  ASSERT_TRUE(same.ok()) << same.status();
  EXPECT_EQ(same->neutral_textures_dir, take + "/same-neutral");
  auto same_albedo = ReadImageFile(same->neutral_textures_dir + "/albedo.exr");
  auto same_normal = ReadImageFile(same->neutral_textures_dir + "/normal_tangent.exr");
  ASSERT_TRUE(same_albedo.ok() && same_normal.ok());
  for (int t = 0; t < 48 * 48; ++t) {
    const float* want = &dataset->textures[t * kTextureChannels];
    ASSERT_EQ(same_albedo->pixels[4 * t + 3], dataset->texture_valid[t]) << t;
    for (int c = 0; c < 3; ++c) ASSERT_EQ(same_albedo->pixels[4 * t + c], want[c]) << t;
    for (int c = 0; c < 3; ++c) ASSERT_EQ(same_normal->pixels[3 * t + c], want[4 + c]) << t;
  }
  auto kept_none = BuildAssetDataset({.take_dir = take,
                                      .output = take + "/none.h5",
                                      .geometry_size = 32,
                                      .texture_size = 48,
                                      .neutral_texture_size = -1});
  ASSERT_TRUE(kept_none.ok()) << kept_none.status();
  EXPECT_EQ(kept_none->neutral_texture_size, 0);
  EXPECT_EQ(ReadAssetDatasetDescription(kept_none->path)->neutral_texture_size, 0);
  EXPECT_FALSE(std::filesystem::exists(take + "/none-neutral"));
  // Without the textures in the truth (or asked for none) the dataset has none, and says why.
  auto none = BuildAssetDataset({.take_dir = MakeTake("asset-no-textures", 3), .geometry_size = 32});
  ASSERT_TRUE(none.ok()) << none.status();
  EXPECT_EQ(none->texture_size, 0);
  EXPECT_THAT(none->textures_note, HasSubstr("--uv-textures"));
  auto off = BuildAssetDataset({.take_dir = take, .geometry_size = 32, .texture_size = 0});
  ASSERT_TRUE(off.ok()) << off.status();
  EXPECT_EQ(off->texture_size, 0);
  EXPECT_EQ(ReadAssetDataset(off->path)->textures.size(), 0u);
  auto neutral_alone =
      BuildAssetDataset({.take_dir = take, .geometry_size = 32, .texture_size = 0, .neutral_texture_size = 64});
  EXPECT_THAT(neutral_alone.status().message(), HasSubstr("neutral texture size 64 with no textures"));
}

TEST(AssetDatasetTest, TheSplitHoldsOutOneSequenceWholeAndEvenContiguousBlocks) {
  std::vector<int32_t> sequence(200);
  for (int i = 0; i < 200; ++i) sequence[i] = i / 25;
  const std::vector<SampleSplit> split = SplitFrames(sequence, 6, 0.2, 5);
  int held_sequence = 0, held_block = 0, runs = 0;
  for (size_t i = 0; i < split.size(); ++i) {
    held_sequence += split[i] == SampleSplit::kHeldOutSequence;
    held_block += split[i] == SampleSplit::kHeldOutBlock;
    if (split[i] == SampleSplit::kHeldOutBlock && (i == 0 || split[i - 1] != SampleSplit::kHeldOutBlock)) ++runs;
    EXPECT_EQ(split[i] == SampleSplit::kHeldOutSequence, sequence[i] == 6) << i;
  }
  EXPECT_EQ(held_sequence, 25);
  EXPECT_EQ(held_block, 35);  // 20 % of 175, in 5 blocks of 7
  EXPECT_EQ(runs, 5);
  // Nothing held out without a sequence and with no fraction.
  for (SampleSplit s : SplitFrames(sequence, -1, 0, 5)) EXPECT_EQ(s, SampleSplit::kTrain);
}

TEST(AssetDatasetTest, ErrorsNameTheTakeTheSequenceAndTheFile) {
  EXPECT_THAT(BuildAssetDataset({.take_dir = ::testing::TempDir() + "/no-take"}).status().message(),
              HasSubstr("no-take: no such take directory"));
  const std::string take = MakeTake("asset-errors", 12);
  EXPECT_THAT(BuildAssetDataset({.take_dir = take, .held_out_sequence = "smile-9"}).status().message(),
              HasSubstr("no frame of sequence \"smile-9\" (seq-0, seq-1)"));
  EXPECT_THAT(BuildAssetDataset({.take_dir = take, .source = AssetSource::kReconstruction}).status().message(),
              HasSubstr("run `stage-process fit` first"));
  EXPECT_THAT(BuildAssetDataset({.take_dir = take, .geometry_size = 8}).status().message(),
              HasSubstr("geometry size 8"));
  EXPECT_THAT(BuildAssetDataset({.take_dir = take, .frame_step = 0}).status().message(),
              HasSubstr("frame step 0 is not in 1..1000"));
  std::filesystem::remove(FrameDir(take + "/ground_truth", 3) + "/pose.json");
  EXPECT_THAT(BuildAssetDataset({.take_dir = take, .held_out_sequence = "none"}).status().message(),
              HasSubstr("frame-000003/pose.json"));
  EXPECT_THAT(ReadAssetDataset(take + "/ground_truth/frame-000000/uv_position.exr").status().message(),
              HasSubstr("not an HDF5 file"));
}

}  // namespace
}  // namespace stage::processing
