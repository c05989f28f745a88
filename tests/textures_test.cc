// Texture fusion as a stage (docs/assets.md#texture-fusion-as-a-stage): a take made of the simulator's truth (the
// true per-pixel maps of the three high-speed cameras as the photometric maps, the face template placed on the true
// surface as the fit, the true cameras as the calibration); the batch command, the worker's job and the library write
// the same bytes, the textures are the head's own, and OpenImageIO's oiiotool reads them.
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <thread>
#include <tuple>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/common/subprocess.h"
#include "stage/common/uv_raster.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"
#include "stage/processing/stabilize.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/texture_fusion.h"
#include "stage/sim/ground_truth.h"
#include "stage/sim/scene.h"
#include "stage/v1/processing_worker.grpc.pb.h"
#include "test_support.h"
#include "worker_support.h"

namespace stage::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

// The take: take.json, ground_truth/ (cameras.json and the three views' maps), derived/photometric (those maps
// under photometric stereo's names) and derived/fit (the template on the true surface). The head of frame 0.
void MakeTake(const std::string& dir, std::shared_ptr<const sim::SimScene>* scene_out) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.render_scale=0.125"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  std::string rig_json;
  ASSERT_TRUE(google::protobuf::util::MessageToJsonString(rig->rig, &rig_json).ok());
  std::ofstream(dir + "/take.json") << nlohmann::json{{"rig", nlohmann::json::parse(rig_json)}}.dump();
  auto scene = sim::SimScene::FromLoadedRig(*rig);
  ASSERT_TRUE(scene.ok()) << scene.status();
  *scene_out = *scene;
  const std::vector<std::string> ids = {"hs-1", "hs-2", "hs-3"};
  ASSERT_TRUE(sim::WriteGroundTruth(**scene, dir + "/ground_truth", {.cameras = ids}).ok());
  for (const std::string& id : ids) {
    const std::string from = dir + "/ground_truth/frame-000000/" + id,
                      to = dir + "/derived/photometric/frame-000000/" + id;
    fs::create_directories(to);
    for (const auto& [a, b] : {std::pair{"albedo", "albedo"},
                               {"normal_world", "diffuse_normal_world"},
                               {"specular", "specular"},
                               {"roughness", "roughness"}}) {
      fs::copy_file(from + "/" + a + ".exr", to + "/" + b + ".exr");
    }
  }
  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  const sim::HeadPose pose = (*scene)->PoseAt(0);
  auto placed = processing::TemplateOnTruth(*face, (*scene)->head()->PosedMesh(pose));
  ASSERT_TRUE(placed.ok()) << placed.status();
  const std::string fit = dir + "/derived/fit/frame-000000";
  fs::create_directories(fit);
  ASSERT_TRUE(WriteObj(fit + "/mesh.obj", *placed).ok());
  std::ofstream(fit + "/pose.json") << R"({"frame": 0, "stage_from_head": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]})";
}

TEST(TexturesStageTest, TheCommandAndTheLibraryFuseTheSameTexturesThatToolsRead) {
  TempDir take;
  std::shared_ptr<const sim::SimScene> scene;
  ASSERT_NO_FATAL_FAILURE(MakeTake(take.path(), &scene));

  CommandResult no_fit = RunCommand({"stage-process", "textures", "--take", take.path(), "--fit", "derived/none"},
                                    std::chrono::seconds(60));
  EXPECT_EQ(no_fit.exit.exit_code, 2);
  EXPECT_THAT(no_fit.err, HasSubstr(take.path() + "/derived/none: no fit (run the fit stage first)"));

  CommandResult batch = RunCommand({"stage-process", "textures", "--take", take.path(), "--calibration", "ground_truth",
                                    "--size", "256", "--output", "derived/textures-batch", "--json"},
                                   std::chrono::seconds(300));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  EXPECT_EQ(nlohmann::json::parse(batch.out)["frames"], 1);
  processing::TexturesJob job;
  job.take_dir = take.path();
  job.calibration = "ground_truth";
  job.options.size = 256;
  job.output_dir = "derived/textures-library";
  auto library = processing::RunTextures(job);
  ASSERT_TRUE(library.ok()) << library.status();
  const auto a = FilesUnder(take.path() + "/derived/textures-batch");
  const auto b = FilesUnder(take.path() + "/derived/textures-library");
  ASSERT_EQ(a.size(), 1 + 9 + 4 + 2u);  // run.json; 9 EXRs, 4 previews, the contact sheet and metrics.json
  for (const auto& [name, bytes] : a) {
    ASSERT_EQ(b.count(name), 1u) << name;
    EXPECT_TRUE(bytes == b.at(name)) << name << " differs between the command and the library";
  }
  // Evaluated against the truth: the maps fused here are the truth's own, so every error is nil; the command checks
  // that the textures on disk are what fusion makes of the maps.
  CommandResult evaluated = RunCommand({"stage-process", "evaluate", "textures", "--take", take.path(), "--textures",
                                        "derived/textures-batch", "--json"},
                                       std::chrono::seconds(120));
  ASSERT_EQ(evaluated.exit.exit_code, 0) << evaluated.err;
  const nlohmann::json all = nlohmann::json::parse(evaluated.out)["frames"][0]["textures"]["all"];
  EXPECT_GT(all["texels"].get<int64_t>(), 256 * 256 / 4);
  EXPECT_LT(all["albedo_mean"].get<double>(), 1e-6);
  EXPECT_LT(all["normal_mean_deg"].get<double>(), 0.01);
  EXPECT_EQ(all["specular_texels"].get<int64_t>(), 0);  // the truth's maps hold no specular normals: no lobe measured
  // Textures that are not what the inputs make (a copy, its albedo replaced) are refused.
  fs::copy(take.path() + "/derived/textures-library", take.path() + "/derived/textures-stale",
           fs::copy_options::recursive);
  fs::copy_file(take.path() + "/derived/textures-stale/frame-000000/roughness.exr",
                take.path() + "/derived/textures-stale/frame-000000/albedo.exr", fs::copy_options::overwrite_existing);
  CommandResult stale = RunCommand(
      {"stage-process", "evaluate", "textures", "--take", take.path(), "--textures", "derived/textures-stale"},
      std::chrono::seconds(120));
  EXPECT_NE(stale.exit.exit_code, 0);
  EXPECT_THAT(stale.err, HasSubstr("albedo.exr: not what fusion makes of"));

  // The worker's job writes the same bytes (into the stage's default directory).
  v1::ProcessingJob request;
  request.set_stage(v1::PROCESSING_STAGE_TEXTURES);
  request.set_take_dir(take.path());
  request.set_calibration("ground_truth");
  request.set_texture_size(256);
  v1::ProcessingProgress last;
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), request, &last));
  EXPECT_TRUE(last.finished());
  EXPECT_EQ(last.output_dir(), take.path() + "/derived/textures");
  const auto w = FilesUnder(take.path() + "/derived/textures");
  ASSERT_EQ(w.size(), b.size());
  for (const auto& [name, bytes] : w) {
    ASSERT_EQ(b.count(name), 1u) << name;
    EXPECT_TRUE(bytes == b.at(name)) << name << " differs between the worker and the library";
  }

  // The fused albedo is the head's own texture (the resampling's error alone: TextureFusionSimTest's figures).
  const std::string frame = take.path() + "/derived/textures-library/frame-000000";
  auto albedo = processing::ReadImageFile(frame + "/albedo.exr");
  ASSERT_TRUE(albedo.ok()) << albedo.status();
  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  const sim::HeadPose pose = scene->PoseAt(0);
  double fused = 0, truth = 0;
  for (int y = 0; y < 256; y += 3) {
    for (int x = 0; x < 256; x += 3) {
      const float a_green = albedo->at(x, y)[1];
      if (a_green <= 0) continue;
      fused += a_green;
      truth += scene->head()->Surface(face->HeadLayoutUv(TexelUv(x, y, 256)), 0, pose.expression).material.albedo.y();
    }
  }
  EXPECT_NEAR(fused / truth, 1, 0.01);
  const nlohmann::json metrics = nlohmann::json::parse(FilesUnder(frame).at("metrics.json"));
  EXPECT_GT(metrics["texels_covered"].get<int64_t>(), 256 * 256 * 9 / 10);
  EXPECT_EQ(metrics["texels_per_view"].size(), 3u);

  // OpenImageIO reads every texture as what it is.
  for (const auto& [file, channels] : {std::pair{"albedo", 3}, {"normal_tangent", 3}, {"roughness", 1}}) {
    CommandResult info =
        RunCommand({"/usr/bin/oiiotool", "--info", frame + "/" + file + ".exr"}, std::chrono::seconds(60));
    ASSERT_EQ(info.exit.exit_code, 0) << info.err;
    EXPECT_THAT(info.out, HasSubstr(absl::StrCat("256 x  256, ", channels, " channel, float openexr"))) << info.out;
  }
}

// The assets open in Blender (headless, Debian's): the fitted OBJ with its texture coordinates, and the textures as
// images whose rows run as Blender's do (its pixel row 0 is v = 0, the bottom: our row size - 1).
// Every image of `t` moved by (dx, dy) texels (zero where it moves in from outside).
processing::FusedTextures Shifted(const processing::FusedTextures& t, int dx, int dy) {
  processing::FusedTextures out = t;
  for (processing::Image* image :
       {&out.albedo, &out.specular, &out.roughness, &out.normal_object, &out.normal_tangent,
        &out.specular_normal_object, &out.specular_normal_tangent, &out.weight, &out.specular_weight}) {
    const processing::Image in = *image;
    std::fill(image->pixels.begin(), image->pixels.end(), 0.0f);
    for (int y = 0; y < in.height; ++y) {
      for (int x = 0; x < in.width; ++x) {
        const int sx = x - dx, sy = y - dy;
        if (sx < 0 || sy < 0 || sx >= in.width || sy >= in.height) continue;
        std::copy_n(in.at(sx, sy), in.channels, image->at(x, y));
      }
    }
  }
  return out;
}

// Stabilization as a stage: frame 1's textures are frame 0's moved by (3, -2) texels; the command, the library and the
// worker's job write the same bytes, and frame 1 comes back onto frame 0.
TEST(TexturesStageTest, StabilizationRunsThreeWaysAndMovesAMovedFrameBack) {
  TempDir take;
  std::shared_ptr<const sim::SimScene> scene;
  ASSERT_NO_FATAL_FAILURE(MakeTake(take.path(), &scene));
  processing::TexturesJob fuse;
  fuse.take_dir = take.path();
  fuse.calibration = "ground_truth";
  fuse.options.size = 128;
  ASSERT_TRUE(processing::RunTextures(fuse).ok());
  const std::string textures = take.path() + "/derived/textures";
  auto frame0 = processing::ReadFusedTextures(textures + "/frame-000000");
  ASSERT_TRUE(frame0.ok()) << frame0.status();
  ASSERT_TRUE(processing::WriteFusedTextures(textures + "/frame-000001", Shifted(*frame0, 3, -2), "{}", "moved").ok());

  CommandResult batch =
      RunCommand({"stage-process", "stabilize", "--take", take.path(), "--output", "derived/stable-batch", "--json"},
                 std::chrono::seconds(120));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  EXPECT_EQ(nlohmann::json::parse(batch.out)["frames"], 2);
  processing::StabilizeJob job;
  job.take_dir = take.path();
  job.output_dir = "derived/stable-library";
  ASSERT_TRUE(processing::RunStabilize(job).ok());

  v1::ProcessingJob request;
  request.set_stage(v1::PROCESSING_STAGE_STABILIZE);
  request.set_take_dir(take.path());
  v1::ProcessingProgress last;
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), request, &last));
  EXPECT_EQ(last.output_dir(), take.path() + "/derived/textures-stable");

  const auto a = FilesUnder(take.path() + "/derived/stable-batch");
  ASSERT_EQ(a.size(), 1 + 2 * (9 + 4 + 2u));  // run.json; per frame 9 EXRs, 4 previews, contact sheet, metrics
  for (const std::string other : {"stable-library", "textures-stable"}) {
    ASSERT_NO_FATAL_FAILURE(ExpectSameFiles(a, take.path() + "/derived/" + other));
  }
  const nlohmann::json metrics = nlohmann::json::parse(a.at("frame-000001/metrics.json"));
  EXPECT_NEAR(metrics["mean_flow_texels"].get<double>(), std::hypot(3, 2), 0.5);
  EXPECT_LT(metrics["albedo_jitter_stabilized"].get<double>(), metrics["albedo_jitter_fused"].get<double>() / 3);
  // The reference frame is written as it was fused.
  EXPECT_TRUE(a.at("frame-000000/albedo.exr") == ReadFile(textures + "/frame-000000/albedo.exr"));

  // The U-Net, three ways (its default training: 300 steps from the flow's warp): the same bytes again (training is
  // deterministic for a seed and a thread count), a wrinkle map per frame and the losses.
  CommandResult unet = RunCommand({"stage-process", "stabilize", "--take", take.path(), "--output",
                                   "derived/unet-batch", "--method", "unet", "--json"},
                                  std::chrono::seconds(600));
  ASSERT_EQ(unet.exit.exit_code, 0) << unet.err;
  job.output_dir = "derived/unet-library";
  job.options.method = processing::StabilizeMethod::kUNet;
  ASSERT_TRUE(processing::RunStabilize(job).ok());
  request.set_stabilize_method(v1::STABILIZE_METHOD_UNET);
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), request, &last));
  const auto u = FilesUnder(take.path() + "/derived/unet-batch");
  ASSERT_EQ(u.size(), a.size() + 2 + 1u);  // and a wrinkle map per frame, loss.csv
  EXPECT_EQ(std::count(u.at("loss.csv").begin(), u.at("loss.csv").end(), '\n'), 301);
  for (const std::string other : {"unet-library", "textures-stable"}) {
    ASSERT_NO_FATAL_FAILURE(ExpectSameFiles(u, take.path() + "/derived/" + other));
  }
  const nlohmann::json unet_metrics = nlohmann::json::parse(u.at("frame-000001/metrics.json"));
  EXPECT_NEAR(unet_metrics["mean_flow_texels"].get<double>(), std::hypot(3, 2), 0.5);
  EXPECT_LT(unet_metrics["albedo_jitter_stabilized"].get<double>(),
            unet_metrics["albedo_jitter_fused"].get<double>() / 3);
  auto wrinkle = processing::ReadImageFile(take.path() + "/derived/unet-batch/frame-000001/wrinkle.exr");
  ASSERT_TRUE(wrinkle.ok()) << wrinkle.status();
  EXPECT_EQ(wrinkle->width, 128);
  EXPECT_EQ(wrinkle->channels, 1);
  // A job that is not stabilization takes no method.
  request.set_stage(v1::PROCESSING_STAGE_FIT);
  EXPECT_NE(RunOnWorkerStatus(take.path(), request).error_message().find("takes no stabilize_method"),
            std::string::npos);
}

TEST(TexturesStageTest, BlenderOpensTheFittedMeshAndItsTextures) {
  TempDir take;
  std::shared_ptr<const sim::SimScene> scene;
  ASSERT_NO_FATAL_FAILURE(MakeTake(take.path(), &scene));
  processing::TexturesJob job;
  job.take_dir = take.path();
  job.calibration = "ground_truth";
  job.options.size = 256;
  ASSERT_TRUE(processing::RunTextures(job).ok());
  const std::string frame = take.path() + "/derived/textures/frame-000000";
  const std::string script = R"(
import bpy, json, sys
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.obj_import(filepath=sys.argv[-3])
obj = bpy.context.selected_objects[0]
me = obj.data
uv = me.uv_layers.active
albedo = bpy.data.images.load(sys.argv[-2])
normal = bpy.data.images.load(sys.argv[-1])
normal.colorspace_settings.name = "Non-Color"
mat = bpy.data.materials.new("face")
mat.use_nodes = True
nodes, links = mat.node_tree.nodes, mat.node_tree.links
base = nodes.new("ShaderNodeTexImage")
base.image = albedo
links.new(base.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
obj.data.materials.append(mat)
w, h = albedo.size
px = albedo.pixels[:]
def at(x, y):  # Blender's row y counts from the bottom
    i = 4 * (y * w + x)
    return px[i:i + 3]
print("RESULT " + json.dumps({"vertices": len(me.vertices), "polygons": len(me.polygons),
                              "uv_loops": len(uv.data) if uv else 0, "size": [w, h], "normal_size": list(normal.size),
                              "bottom_left": at(60, 40), "top_right": at(200, 215)}))
)";
  const std::string mesh = take.path() + "/derived/fit/frame-000000/mesh.obj";
  CommandResult blender = RunCommand({"/usr/bin/blender", "-b", "--factory-startup", "--python-expr", script, "--",
                                      mesh, frame + "/albedo.exr", frame + "/normal_tangent.exr"},
                                     std::chrono::seconds(300));
  ASSERT_EQ(blender.exit.exit_code, 0) << blender.err << blender.out;
  const size_t at = blender.out.find("RESULT ");
  ASSERT_NE(at, std::string::npos) << blender.out << blender.err;
  const nlohmann::json r = nlohmann::json::parse(blender.out.substr(at + 7, blender.out.find('\n', at) - at - 7));
  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  std::printf("Blender: %s\n", r.dump().c_str());
  EXPECT_EQ(r["vertices"], face->mesh.positions.size());
  EXPECT_EQ(r["polygons"], face->mesh.triangles.size());
  EXPECT_EQ(r["uv_loops"], 3 * face->mesh.triangles.size());
  EXPECT_EQ(r["size"], nlohmann::json::array({256, 256}));
  EXPECT_EQ(r["normal_size"], nlohmann::json::array({256, 256}));
  auto albedo = processing::ReadImageFile(frame + "/albedo.exr");
  ASSERT_TRUE(albedo.ok());
  for (const auto& [key, x, y] : {std::tuple{"bottom_left", 60, 40}, {"top_right", 200, 215}}) {
    for (int c = 0; c < 3; ++c) {
      EXPECT_NEAR(r[key][c].get<double>(), albedo->at(x, 255 - y)[c], 1e-4) << key << " channel " << c;
    }
  }
}

}  // namespace
}  // namespace stage::testing
