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
#include "stage/processing/map_files.h"
#include "stage/processing/photometric_stage.h"

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

}  // namespace stage::processing::asset_testing
