// The asset driven from images, on a made-up performance: a face-sized dome whose bulge and jaw follow two slow
// signals of the frame, seen by three cameras as crops where a bright blob's place and size follow the same signals
// (each camera sees it shifted, over its own background). The geometry VAE, the expression VAE (the middle camera held
// out) and the mapping trained in turn drive the geometry from the held-out camera's crops of frames never trained on
// nearer to the geometry VAE's own encoding of the frame than to the neutral frame.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_format.h"
#include "asset_test_support.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/processing/asset_infer.h"
#include "stage/processing/asset_train.h"

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

constexpr int kImage = 32;

float SignalA(int frame) { return std::sin(0.3f * static_cast<float>(frame)); }
float SignalB(int frame) { return std::cos(0.17f * static_cast<float>(frame)); }

Eigen::Vector3f Face(const Eigen::Vector2f& uv, int frame) {
  const float x = 200 * uv.x() - 100, y = 150 * uv.y() - 60;
  const float a = 10 * SignalA(frame), b = 8 * SignalB(frame);
  const float bulge = std::exp(-(x * x + (y - 20) * (y - 20)) / 800), jaw = y < 0 ? -y / 60 : 0;
  return {x, y + b * jaw, 90 - 0.004f * (x * x + y * y) + a * bulge};
}

// Camera c sees the blob shifted by 3 (c - 1) pixels, over a background sloping with c.
float CropPixel(int frame, int camera, int x, int y) {
  const float cx = 16 + 6 * SignalA(frame) + 3.f * static_cast<float>(camera - 1);
  const float radius = 4 + 2 * SignalB(frame);
  const float u = (x + 0.5f) / kImage;
  const float background = 0.1f + 0.15f * static_cast<float>(camera) * u;
  const float d2 = (x - cx) * (x - cx) + (y - 16.f) * (y - 16.f);
  return background + 0.6f * std::exp(-d2 / (radius * radius));
}

std::string Dataset() {
  return asset_testing::WriteMadeUpDataset("drive-take", 80, 32, Face, {"cam-0", "cam-1", "cam-2"}, kImage, CropPixel);
}

TEST(AssetDriveTest, TheAssetDrivenFromAHeldOutCameraComesNearItsCeilingOnFramesNeverTrainedOn) {
  const std::string dataset = Dataset();
  AssetTrainJob geometry;
  geometry.dataset = dataset;
  geometry.geometry = {.input_size = 32,
                       .levels = 3,
                       .base_channels = 8,
                       .max_channels = 32,
                       .geometry_latent = 4,
                       .pose_latent = 3,
                       .threads = 1,
                       .seed = 3};
  geometry.schedule = {.iterations = 200, .batch = 8, .learning_rate = 3e-3, .checkpoint_every = 100};
  // Every texel alike: this made-up face moves as a whole, and a 4-number latent weighting the template's eyes and
  // mouth gives the rest up (the face's ceiling 1.78 mm on the training frames at the default 10, against the neutral
  // frame's 3.36); the driving path, not the weighting, is what this test is about.
  geometry.region_weight = 1;
  ASSERT_TRUE(TrainGeometryAsset(geometry).ok());

  ExpressionTrainJob expression;
  expression.dataset = dataset;
  expression.expression = {.input_size = kImage,
                           .levels = 3,
                           .base_channels = 8,
                           .max_channels = 32,
                           .expression_latent = 4,
                           .view_latent = 2,
                           .threads = 1,
                           .seed = 5};
  expression.held_out_cameras = {"cam-1"};
  expression.schedule = {.iterations = 300, .batch = 8, .learning_rate = 3e-3, .checkpoint_every = 100};
  auto e = TrainExpressionAsset(expression);
  ASSERT_TRUE(e.ok()) << e.status();
  EXPECT_THAT(e->trained_cameras, ::testing::ElementsAre("cam-0", "cam-2"));
  EXPECT_TRUE(std::filesystem::exists(e->output_dir + "/expression_vae.pt"));
  EXPECT_LT(e->evaluation.reconstruction_trained[1], 0.01);

  MappingTrainJob mapping;
  mapping.dataset = dataset;
  mapping.mapping.hidden = 64;
  mapping.mapping.threads = 1;
  mapping.schedule = {.iterations = 600, .batch = 32, .learning_rate = 3e-3, .checkpoint_every = 300};
  auto m = TrainLatentMapping(mapping);
  ASSERT_TRUE(m.ok()) << m.status();
  auto d = ReadAssetDataset(dataset);
  ASSERT_TRUE(d.ok());
  EXPECT_EQ(m->pairs, 2 * std::count(d->split.begin(), d->split.end(), SampleSplit::kTrain));  // by two cameras
  ASSERT_EQ(m->evaluation.cameras.size(), 3u);
  const DrivenEvaluation::Camera& held = m->evaluation.cameras[1];
  EXPECT_EQ(held.id, "cam-1");
  EXPECT_FALSE(held.trained);
  // Driving can come no closer than the geometry VAE's own encoding of the frame's map (the ceiling); from the
  // held-out camera it closes more than half of the gap from the neutral frame to that ceiling.
  for (int split : {1, 2}) {
    const double neutral = m->evaluation.neutral[split].face_mm, ceiling = m->evaluation.autoencoded[split].face_mm;
    EXPECT_GT(held.error[split].frames, 0);
    EXPECT_LT(held.error[split].face_mm, ceiling + 0.5 * (neutral - ceiling))
        << "split " << split << ": driven " << held.error[split].face_mm << " mm, neutral " << neutral
        << ", autoencoded " << ceiling;
  }
  std::cout << FormatDrivenEvaluation(m->evaluation);

  // The third stage: the expression encoder and the mapping fine-tuned together on the geometry latents, the crops
  // jittered. Its loss falls, and from the held-out camera it still closes more than half of the gap (the same bound).
  FineTuneJob finetune;
  finetune.dataset = dataset;
  finetune.driving.threads = 1;
  finetune.schedule = {.iterations = 300, .batch = 16, .learning_rate = 1e-3, .checkpoint_every = 150};
  auto tuned = FineTuneDrivingAsset(finetune);
  ASSERT_TRUE(tuned.ok()) << tuned.status();
  EXPECT_EQ(tuned->pairs, m->pairs);
  ASSERT_EQ(tuned->losses.size(), 300u);
  double first = 0, last = 0;
  for (int i = 0; i < 20; ++i) first += tuned->losses[i], last += tuned->losses[280 + i];
  EXPECT_LT(last, first) << "the fine-tuning's loss did not fall";
  for (int split : {1, 2}) {
    const double neutral = tuned->evaluation.neutral[split].face_mm;
    const double ceiling = tuned->evaluation.autoencoded[split].face_mm;
    EXPECT_LT(tuned->evaluation.cameras[1].error[split].face_mm, ceiling + 0.5 * (neutral - ceiling))
        << "split " << split;
  }
  std::cout << FormatDrivenEvaluation(tuned->evaluation);
  EXPECT_TRUE(std::filesystem::exists(tuned->output_dir + "/driving_net.pt"));
  EXPECT_TRUE(std::filesystem::exists(tuned->output_dir + "/driven.png"));
  auto tuned_again = EvaluateDrivenAsset(dataset, "", "", "", "", "");
  ASSERT_TRUE(tuned_again.ok()) << tuned_again.status();
  EXPECT_DOUBLE_EQ(tuned_again->cameras[1].error[1].face_mm, tuned->evaluation.cameras[1].error[1].face_mm);
  // The paper's choice (the encoder frozen) trains the mapping alone; its finished run loads and evaluates the same.
  FineTuneJob frozen = finetune;
  frozen.driving.train_encoder = false;
  frozen.output_dir = ::testing::TempDir() + "/drive-take/frozen";
  frozen.schedule.iterations = 20;
  auto mapping_alone = FineTuneDrivingAsset(frozen);
  ASSERT_TRUE(mapping_alone.ok()) << mapping_alone.status();
  EXPECT_LT(mapping_alone->parameters, tuned->parameters);
  auto frozen_again = EvaluateDrivenAsset(dataset, "", "", "", "", frozen.output_dir);
  ASSERT_TRUE(frozen_again.ok()) << frozen_again.status();
  EXPECT_DOUBLE_EQ(frozen_again->cameras[1].error[1].face_mm, mapping_alone->evaluation.cameras[1].error[1].face_mm);

  // Driven from a video of the held-out camera (an image sequence; its frames are the crops themselves): a map and a
  // mesh a frame.
  const std::string video = ::testing::TempDir() + "/drive-video";
  std::filesystem::remove_all(video);
  std::filesystem::create_directories(video);
  for (int f = 0; f < 3; ++f) {
    cv::Mat frame(kImage, kImage, CV_8U);
    for (int y = 0; y < kImage; ++y) {
      for (int x = 0; x < kImage; ++x)
        frame.at<uint8_t>(y, x) = cv::saturate_cast<uint8_t>(255 * CropPixel(60 + f, 1, x, y));
    }
    ASSERT_TRUE(cv::imwrite(absl::StrFormat("%s/frame-%04d.png", video, f), frame));
  }
  auto inferred = InferAsset({.dataset = dataset, .camera = "cam-1", .video = video + "/frame-%04d.png"});
  ASSERT_TRUE(inferred.ok()) << inferred.status();
  EXPECT_THAT(inferred->frames, ::testing::ElementsAre(0, 1, 2));
  EXPECT_EQ(inferred->output_dir, ::testing::TempDir() + "/drive-video/frame-%04d-asset");
  EXPECT_THAT(inferred->gltf_files, ::testing::ElementsAre("animation-000000.glb"));
  for (const char* file :
       {"/frame-000002/geometry_map.exr", "/frame-000002/mesh.obj", "/frames.json", "/animation-000000.glb"}) {
    EXPECT_TRUE(std::filesystem::exists(inferred->output_dir + file)) << file;
  }
  {  // Through the fine-tuned path, which the dataset's directory holds.
    std::ifstream in(inferred->output_dir + "/frames.json");
    const std::string frames_json((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    EXPECT_THAT(frames_json, HasSubstr("\"driven_through\": \"finetune\""));
  }
  // Two frames a glTF file: the third frame starts the second.
  auto segmented = InferAsset({.dataset = dataset,
                               .camera = "cam-1",
                               .video = video + "/frame-%04d.png",
                               .output_dir = video + "/segmented",
                               .meshes = false,
                               .gltf_segment_frames = 2});
  ASSERT_TRUE(segmented.ok()) << segmented.status();
  EXPECT_THAT(segmented->gltf_files, ::testing::ElementsAre("animation-000000.glb", "animation-000002.glb"));
  EXPECT_FALSE(std::filesystem::exists(video + "/segmented/frame-000000/mesh.obj"));
  cv::Mat tiny(16, 16, CV_8U, cv::Scalar(10));
  ASSERT_TRUE(cv::imwrite(video + "/tiny-0000.png", tiny));
  EXPECT_THAT(InferAsset({.dataset = dataset, .camera = "cam-1", .video = video + "/tiny-%04d.png"}).status().message(),
              HasSubstr("frames of 16x16 do not hold camera cam-1's crop box"));

  // Runs found by what a later run records: over a copy of the dataset in a directory of its own, with no run beside
  // it, the fine-tuned run named alone evaluates and drives the same (the geometry, expression and mapping runs those
  // it was trained from), the mapping's run named alone too, and a fine-tuning over it finds its VAEs; with no run
  // named, the default is beside the copy, where there is none.
  const std::string elsewhere = ::testing::TempDir() + "/drive-elsewhere";
  std::filesystem::remove_all(elsewhere);
  std::filesystem::create_directories(elsewhere);
  const std::string copy = elsewhere + "/dataset.h5";
  std::filesystem::copy_file(dataset, copy);
  auto recorded = EvaluateDrivenAsset(copy, "", "", "", "", tuned->output_dir);
  ASSERT_TRUE(recorded.ok()) << recorded.status();
  EXPECT_DOUBLE_EQ(recorded->cameras[1].error[1].face_mm, tuned->evaluation.cameras[1].error[1].face_mm);
  auto through_mapping = EvaluateDrivenAsset(copy, "", "", m->output_dir);
  ASSERT_TRUE(through_mapping.ok()) << through_mapping.status();
  EXPECT_DOUBLE_EQ(through_mapping->cameras[1].error[1].face_mm, held.error[1].face_mm);
  auto inferred_elsewhere = InferAsset({.dataset = copy,
                                        .finetune_run = tuned->output_dir,
                                        .camera = "cam-1",
                                        .video = video + "/frame-%04d.png",
                                        .output_dir = elsewhere + "/infer"});
  ASSERT_TRUE(inferred_elsewhere.ok()) << inferred_elsewhere.status();
  EXPECT_EQ(inferred_elsewhere->frames.size(), 3u);
  FineTuneJob over_mapping = finetune;
  over_mapping.dataset = copy;
  over_mapping.mapping_run = m->output_dir;
  over_mapping.output_dir = elsewhere + "/finetune";
  over_mapping.schedule.iterations = 2;
  auto tuned_elsewhere = FineTuneDrivingAsset(over_mapping);
  ASSERT_TRUE(tuned_elsewhere.ok()) << tuned_elsewhere.status();
  EXPECT_THAT(EvaluateDrivenAsset(copy).status().message(), HasSubstr(elsewhere + "/geometry/trainer.json"));
  // The dataset and its four runs copied whole, for below (the original expression run trained again).
  const std::string copied = ::testing::TempDir() + "/drive-copied";
  std::filesystem::remove_all(copied);
  std::filesystem::create_directories(copied);
  std::filesystem::copy_file(dataset, copied + "/dataset.h5");
  for (const char* run : {"geometry", "expression", "mapping", "finetune"}) {
    std::filesystem::copy(std::filesystem::path(dataset).parent_path() / run, copied + "/" + run,
                          std::filesystem::copy_options::recursive);
  }

  // The same evaluation from the finished runs.
  auto again = EvaluateDrivenAsset(dataset);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_DOUBLE_EQ(again->cameras[1].error[1].face_mm, held.error[1].face_mm);

  // The picture, in the mapping's run and where asked: four tiles of 256 under a title; the truth's tile shows the
  // surface (not the background's grey 40) over much of it, the error's tile it in colour.
  const std::string picture = ::testing::TempDir() + "/drive-picture.png";
  ASSERT_TRUE(EvaluateDrivenAsset(dataset, "", "", "", picture).ok());
  for (const std::string& path : {m->output_dir + "/driven.png", picture}) {
    const cv::Mat image = cv::imread(path);
    ASSERT_EQ(image.cols, 4 * 256) << path;
    ASSERT_EQ(image.rows, 256 + 52) << path;
    int surface = 0, coloured = 0;
    for (int y = 52; y < image.rows; ++y) {
      for (int x = 0; x < 256; ++x) {
        surface += image.at<cv::Vec3b>(y, 256 + x) != cv::Vec3b(40, 40, 40);
        const cv::Vec3b colour = image.at<cv::Vec3b>(y, 768 + x);
        coloured += colour[0] != colour[1] || colour[1] != colour[2];
      }
    }
    EXPECT_GT(surface, 256 * 256 / 4) << path;
    EXPECT_GT(coloured, 256 * 256 / 4) << path;
  }

  // A resume finds the run done; over an expression VAE trained again since, it is refused, naming why.
  mapping.schedule.resume = true;
  auto resumed = TrainLatentMapping(mapping);
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_EQ(resumed->resumed_from, 600);
  // Over a run of another directory it names the run it was trained from, and the flag that names it.
  const std::string other = e->output_dir + "-other";
  std::filesystem::copy(e->output_dir, other, std::filesystem::copy_options::recursive);
  std::ofstream(other + "/trainer.json", std::ios::app) << " ";
  const std::string trained_from = std::filesystem::absolute(e->output_dir).lexically_normal().string();
  EXPECT_THAT(EvaluateDrivenAsset(dataset, "", other, "", "", "").status().message(),
              HasSubstr(absl::StrFormat("another expression run than %s: from %s (name it: --expression-run %s)", other,
                                        trained_from, trained_from)));
  std::ofstream(e->output_dir + "/trainer.json", std::ios::app) << " ";
  // The copied tree's fine-tuned run records the original runs; the expression run there is not the very run it
  // recorded any more, so the copy's own beside its dataset is taken, and evaluates as the original did.
  auto copied_tree = EvaluateDrivenAsset(copied + "/dataset.h5", "", "", "", "", copied + "/finetune");
  ASSERT_TRUE(copied_tree.ok()) << copied_tree.status();
  EXPECT_DOUBLE_EQ(copied_tree->cameras[1].error[1].face_mm, tuned->evaluation.cameras[1].error[1].face_mm);
  EXPECT_THAT(TrainLatentMapping(mapping).status().message(), HasSubstr("trained with expression_run_id"));
  EXPECT_THAT(EvaluateDrivenAsset(dataset, "", "", "", "", "").status().message(),
              HasSubstr("fine-tuned from another expression run"));
  EXPECT_THAT(FineTuneDrivingAsset(finetune).status().message(),
              HasSubstr("the mapping was trained from another expression run"));
  EXPECT_THAT(
      InferAsset({.dataset = dataset, .camera = "cam-1", .video = video + "/frame-%04d.png"}).status().message(),
      HasSubstr("fine-tuned from another expression run"));
}

TEST(AssetDriveTest, ErrorsNameTheCameraTheDatasetAndWhatIsMissing) {
  const std::string dataset =
      asset_testing::WriteMadeUpDataset("drive-errors", 20, 32, Face, {"cam-0", "cam-1"}, kImage, CropPixel);
  ExpressionTrainJob job;
  job.dataset = dataset;
  job.expression = {.input_size = kImage, .levels = 3, .max_channels = 32, .threads = 1};
  job.schedule.iterations = 1;
  job.held_out_cameras = {"cam-7"};
  EXPECT_THAT(TrainExpressionAsset(job).status().message(),
              HasSubstr("camera \"cam-7\" is not among its crops' (cam-0, cam-1)"));
  job.held_out_cameras = {"cam-1"};
  EXPECT_THAT(TrainExpressionAsset(job).status().message(), HasSubstr("1 camera(s) left to train on"));
  FineTuneJob finetune;
  finetune.dataset = dataset;
  finetune.map_loss_region_weight = 0.5;
  EXPECT_THAT(FineTuneDrivingAsset(finetune).status().message(),
              HasSubstr("map loss region weight 0.5 is neither 0 nor in 1..1000"));
  job.held_out_cameras = {};
  job.expression.input_size = 64;
  job.expression.levels = 3;
  EXPECT_THAT(TrainExpressionAsset(job).status().message(), HasSubstr("do not divide into the net's 64"));

  MappingTrainJob mapping;
  mapping.dataset = dataset;
  EXPECT_THAT(TrainLatentMapping(mapping).status().message(), HasSubstr("geometry/trainer.json: cannot open"));
  mapping.mapping.input = 3;
  EXPECT_THAT(TrainLatentMapping(mapping).status().message(), HasSubstr("input and output sizes are the VAEs'"));
}

}  // namespace
}  // namespace stage::processing
