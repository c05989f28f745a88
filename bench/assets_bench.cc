// The UV assets of one frame (issue #28: template fit + geometry map + texture fusion <= 10 s on 2 cores at 4096 x
// 4096 textures), beside baselines measured in the same run: reading the inputs the stages read (the surface's OBJ
// and the three views' photometric maps, OpenEXR) and writing the outputs they write (the fitted OBJ, the geometry
// map, the eight 4096 x 4096 textures and their previews). The inputs are the simulator's truth (a performer's true
// mesh, the true maps of hs-1..3), prepared first and not timed.
// Run: build/bin/assets_bench [--render-scale 0.5] [--size 4096] [--identity 5]
#include <chrono>
#include <cstdio>
#include <filesystem>

#include "CLI/CLI.hpp"
#include "stage/common/rig.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/texture_fusion.h"
#include "stage/processing/uv_geometry.h"
#include "stage/sim/ground_truth.h"
#include "stage/sim/scene.h"

namespace {

using Steady = std::chrono::steady_clock;
double Since(Steady::time_point t) { return std::chrono::duration<double>(Steady::now() - t).count(); }

[[noreturn]] void Die(const absl::Status& s) {
  std::fprintf(stderr, "assets_bench: %s\n", std::string(s.message()).c_str());
  std::exit(1);
}

template <typename T>
T Must(absl::StatusOr<T> v) {
  if (!v.ok()) Die(v.status());
  return *std::move(v);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app(
      "The UV assets of one frame (template fit, geometry map, texture fusion) beside reading their inputs "
      "and writing their outputs");
  double render_scale = 0.5;
  int size = 4096, identity = 5;
  app.add_option("--render-scale", render_scale, "The high-speed views' size (1: the whole sensor)")
      ->capture_default_str()
      ->check(CLI::Range(0.05, 1.0));
  app.add_option("--size", size, "Texels across the textures")->capture_default_str()->check(CLI::Range(16, 16384));
  app.add_option("--identity", identity, "The performer (sim.subject.identity)")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  using namespace stage;
  namespace fs = std::filesystem;

  const LoadedRig loaded = Must(LoadRig(kBuiltinRigName));
  const LoadedRig rig = Must(ApplyRigOverrides(
      loaded, {absl::StrCat("sim.render_scale=", render_scale), absl::StrCat("sim.subject.identity=", identity)}));
  const auto scene = Must(sim::SimScene::FromLoadedRig(rig));
  const std::string dir = (fs::temp_directory_path() / absl::StrCat("assets_bench.", getpid())).string();
  const std::vector<std::string> ids = {"hs-1", "hs-2", "hs-3"};
  std::printf("preparing the inputs (a performer's true mesh, the true maps of %zu views at render scale %.2f)...\n",
              ids.size(), render_scale);
  if (auto s = sim::WriteGroundTruth(*scene, dir, {.cameras = ids}); !s.ok()) Die(s);
  if (auto s = WriteObj(dir + "/surface.obj", scene->head()->PosedMesh(scene->PoseAt(0))); !s.ok()) Die(s);

  // Baseline: reading what the stages read.
  auto t = Steady::now();
  const TriangleMesh surface = Must(ReadObj(dir + "/surface.obj"));
  std::vector<processing::FusionView> views;
  for (const std::string& id : ids) {
    processing::FusionView v;
    v.camera_id = id;
    v.camera = scene->camera(scene->CameraIndex(id));
    const std::string maps = dir + "/frame-000000/" + id + "/";
    v.albedo = Must(processing::ReadImageFile(maps + "albedo.exr"));
    v.diffuse_normal = Must(processing::ReadImageFile(maps + "normal_world.exr"));
    v.specular = Must(processing::ReadImageFile(maps + "specular.exr"));
    v.roughness = Must(processing::ReadImageFile(maps + "roughness.exr"));
    views.push_back(std::move(v));
  }
  const double read_s = Since(t);

  const processing::FaceTemplate face = Must(processing::ShippedFaceTemplate());
  t = Steady::now();
  const processing::TemplateFit fit =
      Must(processing::FitTemplate(face, surface, processing::StartAt(face, Eigen::Isometry3f::Identity())));
  const double fit_s = Since(t);
  TriangleMesh fitted = face.mesh;
  fitted.positions = fit.positions;
  t = Steady::now();
  const processing::GeometryMap map = Must(processing::MakeGeometryMap(fitted, fit.stage_from_head.inverse(), {}));
  const double map_s = Since(t);
  processing::FusionOptions options;
  options.size = size;
  t = Steady::now();
  const processing::FusedTextures fused =
      Must(processing::FuseTextures(fitted, fit.stage_from_head.inverse(), views, options));
  const double fuse_s = Since(t);

  // Baseline: writing what the stages write.
  fs::create_directories(dir + "/out");
  t = Steady::now();
  if (auto s = WriteObj(dir + "/out/mesh.obj", fitted); !s.ok()) Die(s);
  if (auto s = processing::WriteGeometryMap(dir + "/out/geometry_map.exr", map); !s.ok()) Die(s);
  if (auto s = processing::WriteFusedTextures(dir + "/out", fused, "{}", "assets_bench"); !s.ok()) Die(s);
  const double write_s = Since(t);
  fs::remove_all(dir);

  const int w = views[0].camera.width(), h = views[0].camera.height();
  std::printf("views: %zu at %d x %d; textures %d x %d; template %zu vertices (%lld matched, %.3f mm rms)\n",
              views.size(), w, h, size, size, face.mesh.positions.size(), static_cast<long long>(fit.matched),
              fit.rms_mm);
  std::printf("template fit (from the stage origin) %7.3f s\n", fit_s);
  std::printf("geometry map (256)                   %7.3f s\n", map_s);
  std::printf("texture fusion                       %7.3f s\n", fuse_s);
  std::printf("  fit + map + fusion                 %7.3f s   (goal 10 s)\n", fit_s + map_s + fuse_s);
  std::printf("baseline: reading the inputs         %7.3f s\n", read_s);
  std::printf("baseline: writing the outputs        %7.3f s\n", write_s);
  return 0;
}
