// The neural asset's dataset from a take the simulator renders (its range-of-motion performance): the geometry maps
// against the truth's surface at every template vertex, and every camera's crop holding the face.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/face_template.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/uv_geometry.h"
#include "stage/sim/rendered_take.h"

namespace stage::processing {
namespace {

TEST(AssetDatasetSimTest, TheTruthsMapsHoldTheHeadAndTheCropsTheFace) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.render_scale=0.08", "sim.subject.performance=range_of_motion"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto scene = sim::SimScene::FromLoadedRig(*rig);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const std::string take = ::testing::TempDir() + "/asset-sim-take";
  std::filesystem::remove_all(take);
  // Frames 200 and 560: two expressions, the head turned and moved.
  ASSERT_TRUE(sim::WriteRenderedTake(*scene, take,
                                     {.first_frame = 200,
                                      .last_frame = 561,
                                      .frame_step = 360,
                                      .cameras = {"mv-01", "mv-04", "mv-09"},
                                      .truth_textures = true,
                                      .uv_size = 512})
                  .ok());
  auto summary = BuildAssetDataset({.take_dir = take, .held_out_fraction = 0, .held_out_sequence = "none"});
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->frames, 2);
  EXPECT_EQ(summary->cameras, (std::vector<std::string>{"mv-01", "mv-04", "mv-09"}));
  auto dataset = ReadAssetDataset(summary->path);
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  auto face = ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());

  for (int i = 0; i < 2; ++i) {
    const int64_t frame = dataset->frame[i];
    // The truth: the template's vertices where they belong on the posed head, in the head's frame.
    const sim::HeadPose pose = (*scene)->PoseAt(frame);
    const TriangleMesh truth = (*scene)->head()->PosedMesh(pose);
    auto on_truth = TemplateOnTruth(*face, truth);
    ASSERT_TRUE(on_truth.ok()) << on_truth.status();
    Eigen::Matrix4f m;
    for (int k = 0; k < 16; ++k) m(k / 4, k % 4) = dataset->stage_from_head[i * 16 + k];
    Eigen::Isometry3f head_from_stage;
    head_from_stage.matrix() = m.inverse();
    GeometryMap map;
    map.size = dataset->geometry_size;
    const size_t texels = static_cast<size_t>(map.size) * map.size;
    for (size_t t = 0; t < texels; ++t) {
      map.points.emplace_back(Eigen::Map<const Eigen::Vector3f>(&dataset->geometry[(i * texels + t) * 3]));
      map.state.push_back(dataset->valid[i * texels + t] ? TexelState::kCovered : TexelState::kEmpty);
    }
    std::vector<double> errors;
    for (size_t v = 0; v < face->mesh.positions.size(); ++v) {
      const std::optional<Eigen::Vector3f> p = SampleGeometryMap(map, face->mesh.uvs[v]);
      ASSERT_TRUE(p.has_value()) << v;
      errors.push_back((*p - head_from_stage * on_truth->positions[v]).norm());
    }
    std::sort(errors.begin(), errors.end());
    double mean = 0;
    for (double e : errors) mean += e / static_cast<double>(errors.size());
    const double p99 = errors[errors.size() * 99 / 100];
    std::printf("frame %lld: template vertices from the dataset's map: mean %.4f mm, p99 %.4f mm\n",
                static_cast<long long>(frame), mean, p99);
    EXPECT_LT(mean, 0.05);
    EXPECT_LT(p99, 0.3);

    // The textures: the head's own albedo at each texel's place in its layout (resampled from the truth's 512
    // texels: pores and freckles are finer than that, so the median is the measure), and tangent-space normals
    // about the surface's (the detail tilts them a little).
    ASSERT_EQ(dataset->texture_size, 128);
    std::vector<double> albedo_errors;
    double mean_z = 0;
    for (int t = 0; t < 128 * 128; ++t) {
      if (!dataset->texture_valid[i * 128 * 128 + t]) continue;
      const float* got = &dataset->textures[(static_cast<size_t>(i) * 128 * 128 + t) * kTextureChannels];
      const Eigen::Vector2f uv((t % 128 + 0.5f) / 128, 1 - (t / 128 + 0.5f) / 128);
      const Eigen::Vector3f want =
          (*scene)->head()->Surface(face->HeadLayoutUv(uv), 0, pose.expression).material.albedo;
      albedo_errors.push_back((Eigen::Vector3f(got[0], got[1], got[2]) - want).norm() / want.norm());
      mean_z += got[6];
    }
    ASSERT_GT(albedo_errors.size(), 128u * 128 / 2);
    mean_z /= static_cast<double>(albedo_errors.size());
    std::nth_element(albedo_errors.begin(), albedo_errors.begin() + albedo_errors.size() / 2, albedo_errors.end());
    const double albedo_median = albedo_errors[albedo_errors.size() / 2];
    std::printf("frame %lld: %zu texture texels; albedo median error %.4f; tangent normals' mean z %.4f\n",
                static_cast<long long>(frame), albedo_errors.size(), albedo_median, mean_z);
    EXPECT_LT(albedo_median, 0.01);
    EXPECT_GT(mean_z, 0.99);

    // Each camera's crop: the face in the middle, bright against the dark stage at the corners.
    const int size = dataset->image_size;
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(dataset->image_valid[i * 3 + c], 1);
      const uint8_t* image = &dataset->images[(static_cast<size_t>(i) * 3 + c) * size * size];
      double centre = 0, corner = 0;
      for (int y = 0; y < 8; ++y) {
        for (int x = 0; x < 8; ++x) {
          centre += image[(size / 2 - 4 + y) * size + size / 2 - 4 + x] / 64.0;
          corner += image[y * size + x] / 64.0;
        }
      }
      EXPECT_GT(centre, 100) << "frame " << frame << " camera " << c;
      EXPECT_LT(corner, 20) << "frame " << frame << " camera " << c;
    }
  }
}

}  // namespace
}  // namespace stage::processing
