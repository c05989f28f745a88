// Training the geometry VAE on a tiny made-up performance: the losses fall, held-out frames come back better than the
// neutral frame does, a killed run resumes bit for bit, a checkpoint of other options is refused, and the decoded
// geometry does not follow a rigid motion of the input.
#include "stage/processing/asset_train.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>

#include "asset_test_support.h"
#include "asset_train_internal.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/face_template.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

// A face-sized dome whose bulge and jaw move with two slow signals of the frame.
Eigen::Vector3f Face(const Eigen::Vector2f& uv, int frame) {
  const float x = 200 * uv.x() - 100, y = 150 * uv.y() - 60;
  const float a = 10 * std::sin(0.3f * frame), b = 8 * std::cos(0.17f * frame);
  const float bulge = std::exp(-(x * x + (y - 20) * (y - 20)) / 800), jaw = y < 0 ? -y / 60 : 0;
  return {x, y + b * jaw, 90 - 0.004f * (x * x + y * y) + a * bulge};
}

std::string Dataset(const std::string& name) {
  const std::string take = asset_testing::MakeTruthTake(name, 60, Face, /*size=*/64);
  auto summary = BuildAssetDataset({.take_dir = take, .geometry_size = 32});
  EXPECT_TRUE(summary.ok()) << summary.status();
  return summary->path;
}

AssetTrainJob TinyJob(const std::string& dataset, const std::string& out) {
  AssetTrainJob job;
  job.dataset = dataset;
  job.output_dir = out;
  job.geometry = {.input_size = 32,
                  .levels = 3,
                  .base_channels = 8,
                  .max_channels = 32,
                  .geometry_latent = 4,
                  .pose_latent = 3,
                  .threads = 1,
                  .seed = 3};
  job.schedule.batch = 8;
  job.schedule.iterations = 150;
  job.schedule.checkpoint_every = 50;
  job.schedule.learning_rate = 3e-3;
  return job;
}

double MeanTotal(const std::vector<GeometryLosses>& l, size_t from, size_t to) {
  double sum = 0;
  for (size_t i = from; i < to; ++i) sum += l[i].total;
  return sum / static_cast<double>(to - from);
}

TEST(AssetTrainTest, TheLossesFallAndHeldOutFramesComeBackBetterThanTheNeutralFrame) {
  const std::string dataset = Dataset("train-take");
  const std::string out = ::testing::TempDir() + "/train-run";
  std::filesystem::remove_all(out);
  int64_t calls = 0;
  AssetTrainJob job = TinyJob(dataset, out);
  job.progress = [&](int64_t step, int64_t total, const GeometryLosses&) {
    EXPECT_EQ(step, ++calls);
    EXPECT_EQ(total, 150);
    return true;
  };
  auto result = TrainGeometryAsset(job);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(calls, 150);
  ASSERT_EQ(result->losses.size(), 150u);
  EXPECT_LT(MeanTotal(result->losses, 130, 150), 0.3 * MeanTotal(result->losses, 0, 20));
  // The last checkpoint only (those before it are removed once trainer.json names a newer one).
  EXPECT_FALSE(std::filesystem::exists(out + "/checkpoint-000100.pt"));
  for (const char* file : {"checkpoint-000150.pt", "trainer.json", "loss.csv", "loss.png", "geometry_vae.pt",
                           "geometry_vae.torchscript.pt", "evaluation.json"}) {
    EXPECT_TRUE(std::filesystem::exists(out + "/" + file)) << file;
  }
  const TrainedEvaluation& e = result->evaluation;
  EXPECT_GT(e.vae[1].frames, 0);
  EXPECT_LT(e.vae[1].rmse_mm, 0.5 * e.neutral[1].rmse_mm);
  EXPECT_LT(e.vae[2].rmse_mm, 0.5 * e.neutral[2].rmse_mm);
  // At the template's vertices too, region by region (the made-up surface moves under the eyes and the mouth).
  EXPECT_GT(e.vae[1].face_mm, 0);
  EXPECT_LT(e.vae[1].face_mm, 0.5 * e.neutral[1].face_mm);
  EXPECT_GT(e.neutral[1].mouth_mm, 0);
  EXPECT_GT(e.neutral[1].eyes_mm, 0);
  // Two signals: PCA with four components holds them nearly exactly; the tiny net comes within a few mm.
  EXPECT_LT(e.pca[1].rmse_mm, 0.5);
  EXPECT_LT(e.vae[1].rmse_mm, 3.0);
  // Each map first moved rigidly (up to 5 degrees and 5 mm): the same geometry, since the encoder aligns its input
  // first (a geometry that followed the pose estimate would shake over a clip).
  EXPECT_GT(e.vae_moved[1].frames, 0);
  EXPECT_NEAR(e.vae_moved[1].rmse_mm, e.vae[1].rmse_mm, 0.02 * e.vae[1].rmse_mm);
}

// The region weight: the texels the eyes' and the mouth's vertices sample weigh as asked, most of the skin's do not;
// trained with it, the tiny net brings those vertices closer on its training frames than without it.
TEST(AssetTrainTest, TheEyesAndTheMouthsTexelsWeighAsAsked) {
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok()) << face.status();
  EXPECT_TRUE(asset_internal::RegionWeights(*face, 64, 1).empty());
  const std::vector<float> w = asset_internal::RegionWeights(*face, 64, 7);
  ASSERT_EQ(w.size(), 64u * 64);
  // The weights sampled as the evaluation samples the maps: 7 only where all four texels weigh 7.
  std::vector<float> map;
  for (int c = 0; c < 3; ++c) map.insert(map.end(), w.begin(), w.end());
  const std::vector<float> ones(w.size(), 1.f);
  int skin = 0, skin_unweighted = 0;
  for (size_t v = 0; v < face->mesh.uvs.size(); ++v) {
    const double sampled = (*asset_internal::SampleNchw(map, ones, 64, face->mesh.uvs[v]))[0];
    if (face->regions[v] != FaceRegion::kSkin) {
      EXPECT_NEAR(sampled, 7, 1e-5) << "vertex " << v;
    } else {
      ++skin;
      skin_unweighted += sampled == 1;
    }
  }
  EXPECT_GT(skin_unweighted, skin * 8 / 10);
  const auto weighted = std::count(w.begin(), w.end(), 7.f);
  EXPECT_GT(weighted, 0);
  EXPECT_LT(weighted, static_cast<std::ptrdiff_t>(w.size() / 5));

  const std::string dataset = Dataset("region-take");
  AssetTrainJob plain = TinyJob(dataset, ::testing::TempDir() + "/region-plain");
  plain.region_weight = 1;
  AssetTrainJob weighted_job = TinyJob(dataset, ::testing::TempDir() + "/region-weighted");
  weighted_job.region_weight = 30;
  auto a = TrainGeometryAsset(plain);
  auto b = TrainGeometryAsset(weighted_job);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  const SplitError& pa = a->evaluation.vae[0];
  const SplitError& pb = b->evaluation.vae[0];
  std::printf("train split, eyes / mouth mm: plain %.3f / %.3f, weighted %.3f / %.3f\n", pa.eyes_mm, pa.mouth_mm,
              pb.eyes_mm, pb.mouth_mm);
  EXPECT_LT(std::hypot(pb.eyes_mm, pb.mouth_mm), std::hypot(pa.eyes_mm, pa.mouth_mm));
  weighted_job.region_weight = 0.5;
  EXPECT_THAT(std::string(TrainGeometryAsset(weighted_job).status().message()),
              HasSubstr("region weight 0.5 is not in 1..1000"));
}

TEST(AssetTrainTest, AKilledRunResumesBitForBitAndOtherOptionsAreRefused) {
  const std::string dataset = Dataset("resume-take");
  const std::string whole = ::testing::TempDir() + "/resume-whole", broken = ::testing::TempDir() + "/resume-broken";
  std::filesystem::remove_all(whole);
  std::filesystem::remove_all(broken);
  AssetTrainJob job = TinyJob(dataset, whole);
  job.schedule.iterations = 40;
  job.schedule.checkpoint_every = 10;
  auto unbroken = TrainGeometryAsset(job);
  ASSERT_TRUE(unbroken.ok()) << unbroken.status();

  job.output_dir = broken;
  job.progress = [](int64_t step, int64_t, const GeometryLosses&) { return step < 25; };
  auto killed = TrainGeometryAsset(job);
  ASSERT_EQ(killed.status().code(), absl::StatusCode::kCancelled) << killed.status();
  job.progress = nullptr;
  job.schedule.resume = true;
  auto resumed = TrainGeometryAsset(job);
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_EQ(resumed->resumed_from, 20);
  ASSERT_EQ(resumed->losses.size(), unbroken->losses.size());
  for (size_t i = 0; i < unbroken->losses.size(); ++i) {
    EXPECT_EQ(resumed->losses[i].total, unbroken->losses[i].total) << "step " << i + 1;
  }
  EXPECT_EQ(resumed->evaluation.vae[1].rmse_mm, unbroken->evaluation.vae[1].rmse_mm);

  job.geometry.geometry_latent = 5;
  auto other = TrainGeometryAsset(job);
  ASSERT_EQ(other.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(other.status().message(), HasSubstr("trained with geometry_latent = 4, not 5"));
}

TEST(AssetTrainTest, TheDecodedGeometryDoesNotFollowARigidMotionOfTheInput) {
  const std::string dataset = Dataset("pose-take");
  const std::string out = ::testing::TempDir() + "/pose-run";
  std::filesystem::remove_all(out);
  AssetTrainJob job = TinyJob(dataset, out);
  job.schedule.iterations = 300;
  ASSERT_TRUE(TrainGeometryAsset(job).ok());
  auto data = ReadAssetDataset(dataset);
  ASSERT_TRUE(data.ok());
  auto mean = std::vector<float>(3 * 32 * 32, 0.f);
  auto net = GeometryVae::Create(job.geometry, mean, 1.f);
  ASSERT_TRUE(net.ok());
  ASSERT_TRUE((*net)->Load(out + "/geometry_vae.pt").ok());
  // Frame 7's map (NCHW), and the same turned 10 degrees about y and moved 6 mm.
  std::vector<float> map(3 * 32 * 32), moved(3 * 32 * 32), valid(32 * 32, 1.f);
  const Eigen::Matrix3f r = Eigen::AngleAxisf(10 * 3.14159265f / 180, Eigen::Vector3f::UnitY()).toRotationMatrix();
  double motion = 0;
  for (int t = 0; t < 32 * 32; ++t) {
    const Eigen::Vector3f p = Eigen::Map<const Eigen::Vector3f>(&data->geometry[(7 * 32 * 32 + t) * 3]);
    const Eigen::Vector3f q = r * p + Eigen::Vector3f(6, 0, 0);
    for (int c = 0; c < 3; ++c) map[c * 1024 + t] = p[c], moved[c * 1024 + t] = q[c];
    motion += (q - p).squaredNorm();
  }
  auto decode = [&](const std::vector<float>& m) {
    auto latents = (*net)->Encode(m, valid, 1);
    EXPECT_TRUE(latents.ok());
    latents->resize(4);
    return *(*net)->Decode(*latents, 1);
  };
  const std::vector<float> a = decode(map), b = decode(moved);
  // Moved back where the input is, the decoded map follows the motion.
  auto reposed = (*net)->Reposed(moved, valid, 1);
  ASSERT_TRUE(reposed.ok()) << reposed.status();
  double reposed_error = 0;
  for (size_t i = 0; i < moved.size(); ++i) reposed_error += std::pow((*reposed)[i] - moved[i], 2);
  EXPECT_LT(std::sqrt(reposed_error / 1024), 2.0);
  double change = 0;
  for (int t = 0; t < 32 * 32; ++t) {
    for (int c = 0; c < 3; ++c) change += std::pow(a[c * 1024 + t] - b[c * 1024 + t], 2);
  }
  // The input moved by this much (RMS); the decoded geometry by a small part of it.
  const double motion_rms = std::sqrt(motion / 1024), change_rms = std::sqrt(change / 1024);
  EXPECT_GT(motion_rms, 8);
  EXPECT_LT(change_rms, 0.2 * motion_rms) << "decoded maps differ by " << change_rms << " mm RMS";
}

// The TorchScript file runs in Python's torch (Debian's python3-torch) without this project's code, and gives what
// the library gives.
TEST(AssetTrainTest, TheExportedNetRunsInPythonsTorchAsInTheLibrary) {
  const std::string dataset = Dataset("script-take");
  const std::string out = ::testing::TempDir() + "/script-run";
  std::filesystem::remove_all(out);
  AssetTrainJob job = TinyJob(dataset, out);
  job.schedule.iterations = 20;
  ASSERT_TRUE(TrainGeometryAsset(job).ok());
  auto net = GeometryVae::Create(job.geometry, std::vector<float>(3 * 32 * 32, 0.f), 1.f);
  ASSERT_TRUE(net.ok());
  ASSERT_TRUE((*net)->Load(out + "/geometry_vae.pt").ok());
  auto data = ReadAssetDataset(dataset);
  ASSERT_TRUE(data.ok());
  // Two frames' maps, NCHW at the net's size (the dataset's 32), all valid.
  std::vector<float> maps(2 * 3 * 1024), valid(2 * 1024, 1.f);
  for (int b = 0; b < 2; ++b) {
    for (int t = 0; t < 1024; ++t) {
      for (int c = 0; c < 3; ++c) maps[(b * 3 + c) * 1024 + t] = data->geometry[((b * 9) * 1024 + t) * 3 + c];
    }
  }
  auto latents = (*net)->Encode(maps, valid, 2);
  ASSERT_TRUE(latents.ok());
  std::vector<float> z;
  for (int b = 0; b < 2; ++b) z.insert(z.end(), latents->begin() + b * 7, latents->begin() + b * 7 + 4);
  auto decoded = (*net)->Decode(z, 2);
  ASSERT_TRUE(decoded.ok());
  auto write = [&](const std::string& name, const std::vector<float>& v) {
    std::ofstream(out + "/" + name, std::ios::binary).write(reinterpret_cast<const char*>(v.data()), v.size() * 4);
  };
  write("maps.f32", maps);
  write("valid.f32", valid);
  write("latents.f32", *latents);
  write("z.f32", z);
  write("decoded.f32", *decoded);
  const std::string script = out + "/check.py";
  std::ofstream(script)
      << "import sys, numpy as np, torch\n"
         "d = sys.argv[1]\n"
         "f = lambda n, *s: torch.from_numpy(np.fromfile(d + '/' + n, dtype=np.float32).reshape(*s))\n"
         "m = torch.jit.load(d + '/geometry_vae.torchscript.pt')\n"
         "with torch.no_grad():\n"
         "    lat = m.encode(f('maps.f32', 2, 3, 32, 32), f('valid.f32', 2, 1, 32, 32))\n"
         "    dec = m(f('z.f32', 2, 4))\n"
         "e1 = (lat - f('latents.f32', 2, 7)).abs().max().item()\n"
         "e2 = (dec - f('decoded.f32', 2, 3, 32, 32)).abs().max().item()\n"
         "print('encode', e1, 'decode', e2)\n"
         "sys.exit(0 if e1 < 1e-3 and e2 < 1e-2 else 1)\n";
  const std::string command = "/usr/bin/python3 " + script + " " + out + " > " + out + "/check.log 2>&1";
  const int rc = std::system(command.c_str());
  std::ifstream log(out + "/check.log");
  const std::string text((std::istreambuf_iterator<char>(log)), std::istreambuf_iterator<char>());
  EXPECT_EQ(rc, 0) << text;
  EXPECT_THAT(text, HasSubstr("encode"));
}

}  // namespace
}  // namespace stage::processing

namespace stage::processing {
namespace {

// Textures that change with two slow signals of the frame, as wrinkles come and go: stripes darken the albedo and
// tilt the normals with one signal, a blotch reddens with the other.
void WriteMadeUpTextures(const std::string& take, int frames, int size) {
  for (int f = 0; f < frames; ++f) {
    const float a = 0.5f + 0.5f * std::sin(0.3f * f), b = 0.5f + 0.5f * std::cos(0.17f * f);
    Image albedo(size, size, 4), material(size, size, 4), normal(size, size, 4);
    for (int y = 0; y < size; ++y) {
      for (int x = 0; x < size; ++x) {
        const float u = (x + 0.5f) / size, v = 1 - (y + 0.5f) / size;
        const float stripe = 0.5f + 0.5f * std::cos(2 * 3.14159265f * v * 6);
        const float blotch = std::exp(-((u - 0.5f) * (u - 0.5f) + (v - 0.4f) * (v - 0.4f)) / 0.01f);
        const float r = 0.6f * (1 - 0.3f * a * stripe) + 0.2f * b * blotch, g = 0.4f * (1 - 0.3f * a * stripe);
        albedo.at(x, y)[0] = r, albedo.at(x, y)[1] = g, albedo.at(x, y)[2] = 0.3f;
        material.at(x, y)[0] = 0.03f + 0.01f * a * stripe;
        // The made-up surface's normal (Face's dome is near +z) tilted along y by the stripes.
        const Eigen::Vector3f n = Eigen::Vector3f(0, 0.3f * a * std::sin(2 * 3.14159265f * v * 6), 1).normalized();
        std::copy(n.data(), n.data() + 3, normal.at(x, y));
        albedo.at(x, y)[3] = material.at(x, y)[3] = normal.at(x, y)[3] = 1;
      }
    }
    const std::string dir = FrameDir(take + "/ground_truth", f);
    EXPECT_TRUE(WriteExr(dir + "/uv_albedo.exr", albedo).ok());
    EXPECT_TRUE(WriteExr(dir + "/uv_material.exr", material).ok());
    EXPECT_TRUE(WriteExr(dir + "/uv_normal.exr", normal).ok());
  }
}

TEST(TextureTrainTest, TheLossesFallAndHeldOutTexturesComeBackBetterThanTheNeutralFrame) {
  const std::string take = asset_testing::MakeTruthTake("texture-take", 60, Face, /*size=*/64);
  WriteMadeUpTextures(take, 60, 64);
  auto summary = BuildAssetDataset({.take_dir = take, .geometry_size = 32, .texture_size = 32});
  ASSERT_TRUE(summary.ok()) << summary.status();
  ASSERT_EQ(summary->texture_size, 32);
  TextureTrainJob job;
  job.dataset = summary->path;
  job.output_dir = ::testing::TempDir() + "/texture-run";
  std::filesystem::remove_all(job.output_dir);
  job.texture = {
      .input_size = 32, .levels = 3, .base_channels = 8, .max_channels = 32, .texture_latent = 4, .threads = 1};
  job.schedule.iterations = 300;
  job.schedule.batch = 8;
  auto result = TrainTextureAsset(job);
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_EQ(result->losses.size(), 300u);
  double first = 0, last = 0;
  for (int i = 0; i < 20; ++i) {
    first += result->losses[i].reconstruction / 20;
    last += result->losses[280 + i].reconstruction / 20;
  }
  EXPECT_LT(last, first / 4) << first << " -> " << last;
  const TextureEvaluation& e = result->evaluation;
  const int held_out = static_cast<int>(SampleSplit::kHeldOutBlock);
  std::printf("held-out blocks: albedo %.3f levels (neutral %.3f, PCA %.3f), normals %.3f deg (neutral %.3f)\n",
              e.vae[held_out].albedo_levels, e.neutral[held_out].albedo_levels, e.pca[held_out].albedo_levels,
              e.vae[held_out].normal_deg, e.neutral[held_out].normal_deg);
  EXPECT_LT(e.vae[held_out].albedo_levels, e.neutral[held_out].albedo_levels / 2);
  EXPECT_LT(e.vae[held_out].normal_deg, e.neutral[held_out].normal_deg / 2);
  EXPECT_TRUE(std::filesystem::exists(job.output_dir + "/texture_vae.pt"));
  // The finished run evaluates again to the same figures.
  auto again = EvaluateTextureAsset(job.dataset, job.output_dir);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_DOUBLE_EQ(again->vae[held_out].albedo_levels, e.vae[held_out].albedo_levels);
  // The exported net runs in Python's torch as in the library.
  auto net = TextureVae::Create(job.texture, std::vector<float>(7 * 32 * 32, 0.f), std::vector<float>(7, 1.f));
  ASSERT_TRUE(net.ok()) << net.status();
  ASSERT_TRUE((*net)->Load(job.output_dir + "/texture_vae.pt").ok());
  auto data = ReadAssetDataset(job.dataset);
  ASSERT_TRUE(data.ok());
  std::vector<float> textures(2 * 7 * 1024), valid(2 * 1024);
  for (int b = 0; b < 2; ++b) {
    for (int t = 0; t < 1024; ++t) {
      valid[b * 1024 + t] = data->texture_valid[(b * 9) * 1024 + t];
      for (int c = 0; c < 7; ++c) textures[(b * 7 + c) * 1024 + t] = data->textures[((b * 9) * 1024 + t) * 7 + c];
    }
  }
  auto latents = (*net)->Encode(textures, valid, 2);
  ASSERT_TRUE(latents.ok());
  auto decoded = (*net)->Decode(*latents, 2);
  ASSERT_TRUE(decoded.ok());
  auto write = [&](const std::string& name, const std::vector<float>& v) {
    std::ofstream(job.output_dir + "/" + name, std::ios::binary)
        .write(reinterpret_cast<const char*>(v.data()), static_cast<std::streamsize>(v.size() * 4));
  };
  write("textures.f32", textures);
  write("valid.f32", valid);
  write("latents.f32", *latents);
  write("decoded.f32", *decoded);
  std::ofstream(job.output_dir + "/check.py")
      << "import sys, numpy as np, torch\n"
         "d = sys.argv[1]\n"
         "f = lambda n, *s: torch.from_numpy(np.fromfile(d + '/' + n, dtype=np.float32).reshape(*s))\n"
         "m = torch.jit.load(d + '/texture_vae.torchscript.pt')\n"
         "with torch.no_grad():\n"
         "    lat = m.encode(f('textures.f32', 2, 7, 32, 32), f('valid.f32', 2, 1, 32, 32))\n"
         "    dec = m(lat)\n"
         "e1 = (lat - f('latents.f32', 2, 4)).abs().max().item()\n"
         "e2 = (dec - f('decoded.f32', 2, 7, 32, 32)).abs().max().item()\n"
         "print('encode', e1, 'decode', e2)\n"
         "sys.exit(0 if e1 < 1e-3 and e2 < 1e-3 else 1)\n";
  const std::string command =
      "/usr/bin/python3 " + job.output_dir + "/check.py " + job.output_dir + " > " + job.output_dir + "/check.log 2>&1";
  const int rc = std::system(command.c_str());
  std::ifstream log(job.output_dir + "/check.log");
  const std::string text((std::istreambuf_iterator<char>(log)), std::istreambuf_iterator<char>());
  EXPECT_EQ(rc, 0) << text;
  EXPECT_THAT(text, HasSubstr("encode"));

  // The textures driven from the geometry: the geometry VAE (default run beside the dataset), then the texture
  // mapping from its latent to the texture latent. The made-up textures follow the same two signals as the geometry.
  AssetTrainJob geometry = TinyJob(job.dataset, "");
  geometry.schedule.iterations = 150;
  ASSERT_TRUE(TrainGeometryAsset(geometry).ok());
  TextureMappingJob mapping;
  mapping.dataset = job.dataset;
  mapping.texture_run = job.output_dir;
  mapping.mapping.hidden = 64;
  mapping.mapping.threads = 1;
  mapping.schedule.iterations = 300;
  mapping.schedule.batch = 16;
  auto mapped = TrainTextureMapping(mapping);
  ASSERT_TRUE(mapped.ok()) << mapped.status();
  const TextureDrivenEvaluation& m = mapped->evaluation;
  std::printf("held-out blocks, textures from the geometry: albedo %.3f levels, normals %.3f deg\n",
              m.from_geometry[held_out].albedo_levels, m.from_geometry[held_out].normal_deg);
  EXPECT_LT(m.from_geometry[held_out].albedo_levels, m.neutral[held_out].albedo_levels / 2);
  EXPECT_LT(m.from_geometry[held_out].normal_deg, m.neutral[held_out].normal_deg / 2);
  EXPECT_TRUE(m.driven_through.empty()) << "no crops, no driving path";
  EXPECT_TRUE(m.cameras.empty());
  auto evaluated = EvaluateDrivenTextures(job.dataset, "", job.output_dir, "");
  ASSERT_TRUE(evaluated.ok()) << evaluated.status();
  EXPECT_DOUBLE_EQ(evaluated->from_geometry[held_out].albedo_levels, m.from_geometry[held_out].albedo_levels);
  // A texture VAE trained again since is not driven through the old mapping.
  job.schedule.iterations = 20;
  ASSERT_TRUE(TrainTextureAsset(job).ok());
  EXPECT_THAT(EvaluateDrivenTextures(job.dataset, "", job.output_dir, "").status().message(),
              HasSubstr("train it again"));
  // A dataset without textures is refused, saying how to get them.
  TextureTrainJob bare = job;
  bare.dataset = Dataset("texture-bare");
  EXPECT_THAT(TrainTextureAsset(bare).status().message(), HasSubstr("--uv-textures"));
}

}  // namespace
}  // namespace stage::processing
