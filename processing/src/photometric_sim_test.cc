// Photometric stereo on the simulated stage: a subject as hs-2 records it (12-bit Bayer), rendered by the simulator in
// process, demosaiced, solved, and compared with the ground truth of the same pixels (the shading normal and albedo
// the renderer used). On the simulator's sphere with (almost) no noise the solver's model must match the renderer's
// exactly once the surface points are known; on the procedural head (full-on 4000 e-, read noise 5 e-) this says
// where the solver stands.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/processing/photometric.h"
#include "stage/sim/light_transport.h"
#include "stage/sim/scene.h"

namespace stage::processing {
namespace {

struct Result {
  double mean = 0, median = 0, p90 = 0, albedo = 0;
  size_t pixels = 0;
};

// Renders the 38 patterns of virtual frame 0 for hs-2 with `overrides`, solves with the dome's directions from its
// centre (`far`) and with each pixel's surface point (`near`), and measures both on the skin (or the whole subject).
void RenderAndSolve(const std::vector<std::string>& overrides, const std::string& label, Result* far_result,
                    Result* near_result) {
  auto builtin = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(builtin.ok());
  std::vector<std::string> all = {"sim.render_scale=0.125", "sim.subject.performance=still"};
  all.insert(all.end(), overrides.begin(), overrides.end());
  auto loaded = ApplyRigOverrides(*builtin, all);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  for (auto& c : *loaded->rig.mutable_cameras()) {
    if (c.id() == "hs-2") c.set_pixel_format(v1::PIXEL_FORMAT_BAYER_RG12);
  }
  auto scene = sim::SimScene::FromLoadedRig(*loaded);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const int index = (*scene)->CameraIndex("hs-2");
  ASSERT_GE(index, 0);
  sim::CameraRenderer renderer(*scene, index);
  const sim::SensorParams& sensor = (*scene)->sensor(index);
  ASSERT_EQ(sensor.bits, 12);
  const double exposure_s = (*scene)->base().TicksToNs((*scene)->schedule().cameras(index).exposure_ticks()) * 1e-9;
  auto light = LightModel::FromRig(*loaded);
  ASSERT_TRUE(light.ok()) << light.status();

  std::vector<Image> frames;
  for (int p = 0; p < static_cast<int>(light->patterns.size()); ++p) {
    const sim::RawImage raw = renderer.Render((*scene)->PatternLevels(p), exposure_s, static_cast<uint64_t>(p), 0);
    cv::Mat mosaic(raw.height, raw.width, CV_16U, const_cast<uint16_t*>(raw.data.data()));
    cv::Mat bgr;
    cv::cvtColor(mosaic, bgr, cv::COLOR_BayerBG2BGR);  // GenICam BayerRG is OpenCV's BayerBG
    Image img(raw.width, raw.height, 3);
    for (int y = 0; y < raw.height; ++y) {
      for (int x = 0; x < raw.width; ++x) {
        const cv::Vec3w v = bgr.at<cv::Vec3w>(y, x);
        float* o = img.at(x, y);
        for (int c = 0; c < 3; ++c) o[c] = static_cast<float>(v[2 - c]) - static_cast<float>(sensor.black_level_dn);
      }
    }
    frames.push_back(std::move(img));
  }
  const CameraModel& cam = (*scene)->camera(index);
  PhotometricCamera pc;
  pc.world_to_camera = cam.rotation();
  pc.position_mm = cam.position();
  double z = 0;
  const Eigen::Vector3d toward = cam.position().normalized();
  for (size_t l = 0; l < light->directions.size(); ++l)
    z += light->intensity[l] * std::max(0.0, toward.dot(light->directions[l]));
  pc.gain_e_per_dn = sensor.Gain();
  pc.white_scale = loaded->rig.sim().full_on_electrons() / sensor.Gain() / z;
  pc.read_noise_e = loaded->rig.sim().read_noise_e();
  pc.saturation_dn = (1 << sensor.bits) - 1 - sensor.black_level_dn;
  pc.cross_leak = (*scene)->leakage(index);
  const std::vector<sim::Hit> hits = sim::TracePixels(cam, *(*scene)->SubjectAt(0));
  Image positions(frames[0].width, frames[0].height, 3);
  for (size_t i = 0; i < hits.size(); ++i) {
    if (!hits[i].hit) continue;
    std::copy(hits[i].point.data(), hits[i].point.data() + 3, &positions.pixels[i * 3]);
  }
  auto evaluate = [&](const PhotometricMaps& maps) {
    std::vector<double> errors;
    double albedo_rel = 0;
    for (int y = 0; y < maps.height; ++y) {
      for (int x = 0; x < maps.width; ++x) {
        const sim::Hit& hit = hits[static_cast<size_t>(y) * maps.width + x];
        if (!hit.hit || hit.part != 0) continue;  // skin (the sphere is all part 0)
        const float* n = maps.diffuse_normal_world.at(x, y);
        if (n[0] == 0 && n[1] == 0 && n[2] == 0) continue;
        errors.push_back(AngleDeg(hit.normal.cast<double>(), Eigen::Vector3d(n[0], n[1], n[2])));
        const float* a = maps.albedo.at(x, y);
        for (int c = 0; c < 3; ++c) albedo_rel += std::abs(a[c] / hit.material.albedo[c] - 1) / 3;
      }
    }
    Result r;
    r.pixels = errors.size();
    if (errors.empty()) return r;
    for (double e : errors) r.mean += e;
    r.mean /= static_cast<double>(errors.size());
    r.albedo = albedo_rel / static_cast<double>(errors.size());
    std::sort(errors.begin(), errors.end());
    r.median = errors[errors.size() / 2];
    r.p90 = errors[errors.size() * 9 / 10];
    return r;
  };
  // With the dome's directions from its centre (the table), and with each pixel's surface point known.
  auto far = SolvePhotometric(*light, frames, pc);
  ASSERT_TRUE(far.ok()) << far.status();
  auto near = SolvePhotometric(*light, frames, pc, {}, &positions);
  ASSERT_TRUE(near.ok()) << near.status();
  *far_result = evaluate(*far);
  *near_result = evaluate(*near);
  for (const auto& [name, r] :
       {std::pair<const char*, Result>{"units from the centre", *far_result}, {"surface points", *near_result}}) {
    std::printf(
        "%s, hs-2, %s (%zu pixels): normals mean %.2f deg, median %.2f deg, 90th percentile %.2f deg; "
        "albedo %.2f %%\n",
        label.c_str(), name, r.pixels, r.mean, r.median, r.p90, 100 * r.albedo);
  }
}

// The simulator's sphere (100 mm, no self-shadowing) with noise made negligible: the solver's model is the renderer's.
TEST(PhotometricSimTest, OnTheRenderedSphereTheModelIsTheRenderers) {
  Result far, near;
  ASSERT_NO_FATAL_FAILURE(RenderAndSolve(
      {"sim.subject.kind=sphere", "sim.full_on_electrons=1000000", "sim.full_well_e=2500000", "sim.read_noise_e=0.1"},
      "sphere", &far, &near));
  EXPECT_GT(near.pixels, 20000u);
  EXPECT_LT(near.mean, 0.3);
  EXPECT_LT(near.albedo, 0.01);
  // From the dome's centre the units' real distance (the sphere's surface is 100 mm from it) costs degrees.
  EXPECT_GT(far.mean, 1.0);
}

TEST(PhotometricSimTest, TheProceduralHeadAgainstGroundTruth) {
  Result far, near;
  ASSERT_NO_FATAL_FAILURE(RenderAndSolve({}, "head", &far, &near));
  EXPECT_GT(near.pixels, 40000u);
  // Where the solver stands (issue #6's goals, 1.5 deg and 0.7 %, are not met yet): the units' real distance halves
  // the error; what remains is self-shadowing (the nose hides a quarter of the dome from the cheeks beside it).
  EXPECT_LT(far.mean, 7.0);
  EXPECT_LT(near.mean, 3.5);
  EXPECT_LT(near.median, 2.5);
  EXPECT_LT(near.mean, 0.7 * far.mean);
}

}  // namespace
}  // namespace stage::processing
