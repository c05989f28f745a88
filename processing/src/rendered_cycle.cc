#include "rendered_cycle.h"

#include <algorithm>
#include <cmath>

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/processing/calibration.h"
#include "stage/processing/take_frames.h"

namespace stage::processing {

void RenderCycle(const std::string& camera_id, const std::vector<std::string>& overrides, RenderedCycle* out) {
  auto builtin = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(builtin.ok());
  std::vector<std::string> all = {"sim.render_scale=0.125", "sim.subject.performance=still"};
  all.insert(all.end(), overrides.begin(), overrides.end());
  auto loaded = ApplyRigOverrides(*builtin, all);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  for (auto& c : *loaded->rig.mutable_cameras()) {
    if (c.id() == camera_id) c.set_pixel_format(v1::PIXEL_FORMAT_BAYER_RG12);
  }
  auto scene = sim::SimScene::FromLoadedRig(*loaded);
  ASSERT_TRUE(scene.ok()) << scene.status();
  out->scene = *scene;
  const int index = (*scene)->CameraIndex(camera_id);
  ASSERT_GE(index, 0) << camera_id;
  out->index = index;
  sim::CameraRenderer renderer(*scene, index);
  const sim::SensorParams& sensor = (*scene)->sensor(index);
  ASSERT_EQ(sensor.bits, 12);
  const double exposure_s = (*scene)->base().TicksToNs((*scene)->schedule().cameras(index).exposure_ticks()) * 1e-9;
  auto made = LightModel::FromRig(*loaded);
  ASSERT_TRUE(made.ok()) << made.status();
  out->light = *made;
  const LightModel& light = out->light;
  const CameraModel& cam = (*scene)->camera(index);
  // The camera as the pipeline sees it: placed where it is (as a perfect calibration finds it), its radiometric
  // calibration derived from the simulator's sensor model.
  auto setup = ResolveCamera(*loaded, light, camera_id, cam.width(), cam.height(), 12, &(*scene)->true_cameras());
  ASSERT_TRUE(setup.ok()) << setup.status();
  EXPECT_EQ(setup->source, "simulator");
  EXPECT_NEAR(setup->camera.gain_e_per_dn, sensor.Gain(), 1e-9 * sensor.Gain());
  EXPECT_NEAR(setup->camera.cross_leak, (*scene)->leakage(index), 1e-6);
  EXPECT_EQ(setup->black_level_dn, sensor.black_level_dn);
  out->camera = setup->camera;
  out->camera.mosaic = Mosaic{};  // RGGB, as demosaiced below

  for (int p = 0; p < static_cast<int>(light.patterns.size()); ++p) {
    const sim::RawImage raw = renderer.Render((*scene)->PatternLevels(p), exposure_s, static_cast<uint64_t>(p), 0);
    std::vector<float> mosaic(raw.data.size());
    for (size_t i = 0; i < mosaic.size(); ++i) {
      mosaic[i] = static_cast<float>(raw.data[i]) - static_cast<float>(sensor.black_level_dn);
    }
    Image img;
    DemosaicBilinear(mosaic.data(), raw.width, raw.height, Mosaic{}, &img);  // RGGB
    out->frames.push_back(std::move(img));
  }
  const std::shared_ptr<const sim::Subject> subject = (*scene)->SubjectAt(0);
  out->hits = sim::TracePixels(cam, *subject);
  // With n x n rays a pixel (sim.supersample), the truth of a pixel is its rays' mean normal and material, as the
  // ground truth files have it.
  const int n = static_cast<int>(loaded->rig.sim().supersample());
  if (n > 1) {
    std::vector<Eigen::Vector3f> normal(out->hits.size(), Eigen::Vector3f::Zero()), albedo(normal);
    std::vector<float> specular(out->hits.size(), 0), roughness(out->hits.size(), 0);
    std::vector<int> count(out->hits.size(), 0);
    for (int sy = 0; sy < n; ++sy) {
      for (int sx = 0; sx < n; ++sx) {
        const auto rays = sim::TracePixels(cam, *subject, 0, (sx + 0.5) / n - 0.5, (sy + 0.5) / n - 0.5);
        for (size_t i = 0; i < rays.size(); ++i) {
          if (!rays[i].hit) continue;
          normal[i] += rays[i].normal;
          albedo[i] += rays[i].material.albedo;
          specular[i] += rays[i].material.specular;
          roughness[i] += rays[i].material.roughness;
          ++count[i];
        }
      }
    }
    for (size_t i = 0; i < out->hits.size(); ++i) {
      // Only pixels the subject fills: an edge pixel mixes in the background.
      if (!out->hits[i].hit || count[i] < n * n) {
        out->hits[i].hit = false;
        continue;
      }
      out->hits[i].normal = normal[i].normalized();
      out->hits[i].material.albedo = albedo[i] / static_cast<float>(count[i]);
      out->hits[i].material.specular = specular[i] / static_cast<float>(count[i]);
      out->hits[i].material.roughness = roughness[i] / static_cast<float>(count[i]);
    }
  }
  // The geometry as the simulator has it: the point each pixel's ray lands on, and every unit in front of its face
  // that nothing hides.
  PixelGeometry& g = out->truth_geometry;
  g.width = cam.width();
  g.height = cam.height();
  g.words = (light.units() + 63) / 64;
  const std::vector<sim::Hit> centre = sim::TracePixels(cam, *subject);
  g.points.assign(3 * centre.size(), std::nanf(""));
  g.visible.assign(centre.size() * static_cast<size_t>(g.words), 0);
  for (size_t i = 0; i < centre.size(); ++i) {
    const sim::Hit& hit = centre[i];
    if (!hit.hit) continue;
    std::copy(hit.point.data(), hit.point.data() + 3, &g.points[3 * i]);
    const Eigen::Vector3f start = hit.point + 1e-3f * hit.geometric_normal;
    for (int l = 0; l < light.units(); ++l) {
      const Eigen::Vector3f unit = (light.directions[static_cast<size_t>(l)] * light.radius_mm).cast<float>();
      if (hit.geometric_normal.dot(unit - hit.point) <= 0 || subject->Occluded(start, unit)) continue;
      g.visible[i * static_cast<size_t>(g.words) + static_cast<size_t>(l) / 64] |= uint64_t{1} << (l % 64);
    }
  }
}

}  // namespace stage::processing
