// Made-up takes for the neural asset's tests: a simulator-shaped truth (ground_truth/frame-NNNNNN/uv_position.exr and
// pose.json) whose surface is a function the test gives, so what a dataset or a net should recover is known.
#pragma once

#include <Eigen/Geometry>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>

#include "gtest/gtest.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/map_files.h"
#include "stage/processing/photometric_stage.h"
#include "stage/storage/array_file.h"

namespace stage::processing::asset_testing {

// The head's pose in frame `frame`: a slow turn about y and a shift.
inline Eigen::Isometry3f MadeUpPose(int64_t frame) {
  Eigen::Isometry3f pose = Eigen::Isometry3f::Identity();
  pose.linear() = Eigen::AngleAxisf(0.01f * static_cast<float>(frame), Eigen::Vector3f::UnitY()).toRotationMatrix();
  pose.translation() = Eigen::Vector3f(static_cast<float>(frame), 2, -3);
  return pose;
}

// A take under the test's temporary directory of `frames` frames of truth (`size` texels across the head's layout):
// frame f's surface in the head's frame at head-layout uv is surface(uv, f), posed by MadeUpPose(f); sequences of
// `per_sequence` frames named "seq-K". Returns the take's directory.
inline std::string MakeTruthTake(const std::string& name, int frames,
                                 const std::function<Eigen::Vector3f(const Eigen::Vector2f&, int)>& surface,
                                 int size = 128, int per_sequence = 10) {
  const std::string take = ::testing::TempDir() + "/" + name;
  std::filesystem::remove_all(take);
  for (int f = 0; f < frames; ++f) {
    const std::string dir = FrameDir(take + "/ground_truth", f);
    std::filesystem::create_directories(dir);
    const Eigen::Isometry3f stage_from_head = MadeUpPose(f);
    Image map(size, size, 4);
    for (int y = 0; y < size; ++y) {
      for (int x = 0; x < size; ++x) {
        const Eigen::Vector2f uv((x + 0.5f) / size, 1 - (y + 0.5f) / size);
        const Eigen::Vector3f p = stage_from_head * surface(uv, f);
        float* t = map.at(x, y);
        t[0] = p.x(), t[1] = p.y(), t[2] = p.z(), t[3] = 1;
      }
    }
    EXPECT_TRUE(WriteExr(dir + "/uv_position.exr", map).ok());
    nlohmann::json j;
    j["sequence"] = "seq-" + std::to_string(f / per_sequence);
    for (int i = 0; i < 16; ++i) j["stage_from_head"].push_back(stage_from_head.matrix()(i / 4, i % 4));
    std::ofstream(dir + "/pose.json") << j.dump();
  }
  return take;
}

// A dataset file written directly (as BuildAssetDataset writes one): `frames` frames of `size`-texel geometry maps
// (surface(uv, frame), the head's frame; every texel valid), and crops of `image_size` pixels by each of `cameras`
// (crop(frame, camera, x, y), 0..1), sequences of `per_sequence` frames "seq-K", the last held out whole and a fifth
// of the rest in two blocks. Returns the file's path.
inline std::string WriteMadeUpDataset(const std::string& name, int frames, int size,
                                      const std::function<Eigen::Vector3f(const Eigen::Vector2f&, int)>& surface,
                                      const std::vector<std::string>& cameras, int image_size,
                                      const std::function<float(int, int, int, int)>& crop, int per_sequence = 10) {
  using storage::ArrayType;
  const std::string dir = ::testing::TempDir() + "/" + name;
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  const std::string path = dir + "/dataset.h5";
  auto writer = storage::ArrayFileWriter::Create(path);
  EXPECT_TRUE(writer.ok()) << writer.status();
  const int64_t views = static_cast<int64_t>(cameras.size());
  EXPECT_TRUE((*writer)->AddArray("frame", ArrayType::kInt64, {}).ok());
  EXPECT_TRUE((*writer)->AddArray("split", ArrayType::kUint8, {}).ok());
  EXPECT_TRUE((*writer)->AddArray("sequence", ArrayType::kInt32, {}).ok());
  EXPECT_TRUE((*writer)->AddArray("geometry", ArrayType::kFloat32, {size, size, 3}).ok());
  EXPECT_TRUE((*writer)->AddArray("valid", ArrayType::kUint8, {size, size}).ok());
  EXPECT_TRUE((*writer)->AddArray("stage_from_head", ArrayType::kFloat32, {4, 4}).ok());
  EXPECT_TRUE((*writer)->AddArray("images", ArrayType::kUint8, {views, image_size, image_size}).ok());
  EXPECT_TRUE((*writer)->AddArray("image_valid", ArrayType::kUint8, {views}).ok());
  std::vector<int32_t> sequence;
  std::vector<std::string> names;
  for (int f = 0; f < frames; ++f) sequence.push_back(f / per_sequence);
  for (int k = 0; k <= (frames - 1) / per_sequence; ++k) names.push_back("seq-" + std::to_string(k));
  const std::vector<SampleSplit> split = SplitFrames(sequence, sequence.back(), 0.2, 2);
  for (int f = 0; f < frames; ++f) {
    const int64_t frame = f;
    const uint8_t s = static_cast<uint8_t>(split[f]);
    std::vector<float> geometry;
    for (int y = 0; y < size; ++y) {
      for (int x = 0; x < size; ++x) {
        const Eigen::Vector3f p = surface({(x + 0.5f) / size, 1 - (y + 0.5f) / size}, f);
        geometry.insert(geometry.end(), {p.x(), p.y(), p.z()});
      }
    }
    const std::vector<uint8_t> valid(static_cast<size_t>(size) * size, 1), image_valid(cameras.size(), 1);
    std::vector<float> pose(16, 0.f);
    for (int i = 0; i < 4; ++i) pose[i * 5] = 1;
    std::vector<uint8_t> images;
    for (int c = 0; c < static_cast<int>(views); ++c) {
      for (int y = 0; y < image_size; ++y) {
        for (int x = 0; x < image_size; ++x) {
          images.push_back(static_cast<uint8_t>(std::clamp(255 * crop(f, c, x, y) + 0.5f, 0.f, 255.f)));
        }
      }
    }
    EXPECT_TRUE((*writer)->Append("frame", &frame).ok());
    EXPECT_TRUE((*writer)->Append("split", &s).ok());
    EXPECT_TRUE((*writer)->Append("sequence", &sequence[f]).ok());
    EXPECT_TRUE((*writer)->Append("geometry", geometry.data()).ok());
    EXPECT_TRUE((*writer)->Append("valid", valid.data()).ok());
    EXPECT_TRUE((*writer)->Append("stage_from_head", pose.data()).ok());
    EXPECT_TRUE((*writer)->Append("images", images.data()).ok());
    EXPECT_TRUE((*writer)->Append("image_valid", image_valid.data()).ok());
  }
  // Each camera's frames are its crops: the box is the whole frame, white at full scale.
  nlohmann::json boxes = nlohmann::json::array();
  for (const std::string& id : cameras) {
    boxes.push_back({{"camera", id},
                     {"centre_px", {image_size / 2.0, image_size / 2.0}},
                     {"side_px", image_size},
                     {"white_dn", 255.0}});
  }
  nlohmann::json description = {{"source", "truth"},  {"take", name},       {"geometry_size", size},
                                {"sequences", names}, {"cameras", cameras}, {"image_size", image_size},
                                {"crops", boxes}};
  EXPECT_TRUE((*writer)->SetAttribute("format", "fastage-asset-dataset-1").ok());
  EXPECT_TRUE((*writer)->SetAttribute("description", description.dump()).ok());
  EXPECT_TRUE((*writer)->Close().ok());
  return path;
}

}  // namespace stage::processing::asset_testing
