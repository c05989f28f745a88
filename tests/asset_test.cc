// The neural asset's stages three ways (stage-process asset ..., the library, the processing worker's job) on a take
// the simulator renders: the dataset, the geometry VAE, the expression VAE, the mapping, the fine-tuning, the texture
// VAE and the texture mapping give the same bytes each
// way; the dataset opens in h5py; clear errors.
#include <tiny_gltf.h>

#include <cmath>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/mesh.h"
#include "stage/common/rig.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/asset_infer.h"
#include "stage/processing/asset_train.h"
#include "stage/processing/face_template.h"
#include "stage/processing/map_files.h"
#include "stage/sim/rendered_take.h"
#include "test_support.h"
#include "worker_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

// Frame k of a driven sequence's glTF (mesh_sequence.h), in mm: its rest positions moved by morph target k.
std::vector<Eigen::Vector3f> GlbFrame(const std::string& path, int k) {
  tinygltf::TinyGLTF loader;
  tinygltf::Model model;
  std::string error, warning;
  EXPECT_TRUE(loader.LoadBinaryFromFile(&model, &error, &warning, path)) << path << ": " << error;
  if (model.meshes.size() != 1) return {};
  const tinygltf::Primitive& primitive = model.meshes[0].primitives.at(0);
  auto floats = [&model](int accessor) {
    const tinygltf::Accessor& a = model.accessors.at(accessor);
    const tinygltf::BufferView& view = model.bufferViews.at(a.bufferView);
    const auto* data =
        reinterpret_cast<const float*>(model.buffers.at(view.buffer).data.data() + view.byteOffset + a.byteOffset);
    return std::vector<float>(data, data + 3 * a.count);
  };
  const std::vector<float> rest = floats(primitive.attributes.at("POSITION"));
  const std::vector<float> offset = floats(primitive.targets.at(k).at("POSITION"));
  std::vector<Eigen::Vector3f> out(rest.size() / 3);
  for (size_t v = 0; v < out.size(); ++v) {
    for (int c = 0; c < 3; ++c) out[v][c] = 1000 * (rest[3 * v + c] + offset[3 * v + c]);
  }
  return out;
}

// Twelve frames of the range-of-motion performance, 100 s apart by 8 s, seen by two machine-vision cameras.
void MakeTake(const std::string& dir) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(
      *loaded, {"sim.render_scale=0.05", "sim.subject.performance=range_of_motion", "sim.subject.head_resolution=96"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto scene = sim::SimScene::FromLoadedRig(*rig);
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_TRUE(sim::WriteRenderedTake(*scene, dir,
                                     {.first_frame = 0,
                                      .last_frame = 2400,
                                      .frame_step = 200,
                                      .cameras = {"mv-01", "mv-05"},
                                      .truth_textures = true,
                                      .uv_size = 128})
                  .ok());
}

TEST(AssetStageTest, TheDatasetAndTheTrainingRunThreeWaysToTheSameBytes) {
  TempDir take;
  ASSERT_NO_FATAL_FAILURE(MakeTake(take.path()));
  const std::string asset = take.path() + "/derived/asset";

  // The dataset.
  CommandResult batch = RunCommand(
      {"stage-process", "asset", "build-dataset", "--take", take.path(), "--geometry-size", "32", "--image-size", "32",
       "--texture-size", "32", "--crop-mm", "300", "--output", asset + "/batch.h5", "--json"},
      std::chrono::seconds(120));
  ASSERT_EQ(batch.exit.exit_code, 0) << batch.err;
  const nlohmann::json summary = nlohmann::json::parse(batch.out);
  EXPECT_EQ(summary["frames"], 12);
  EXPECT_EQ(summary["cameras"].size(), 2u);
  EXPECT_EQ(summary["texture_size"], 32);
  processing::DatasetOptions options{.take_dir = take.path(),
                                     .output = asset + "/library.h5",
                                     .geometry_size = 32,
                                     .texture_size = 32,
                                     .image_size = 32,
                                     .crop_mm = 300};
  ASSERT_TRUE(processing::BuildAssetDataset(options).ok());
  v1::ProcessingJob request;
  request.set_stage(v1::PROCESSING_STAGE_ASSET_DATASET);
  request.set_take_dir(take.path());
  request.mutable_asset()->set_geometry_size(32);
  request.mutable_asset()->set_image_size(32);
  request.mutable_asset()->set_crop_mm(300);
  request.set_texture_size(32);
  v1::ProcessingProgress last;
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/dataset.h5");
  const std::string dataset = ReadFile(asset + "/dataset.h5");
  EXPECT_TRUE(ReadFile(asset + "/batch.h5") == dataset);
  EXPECT_TRUE(ReadFile(asset + "/library.h5") == dataset);
  CommandResult h5py =
      RunCommand({"/usr/bin/python3", "-c",
                  "import h5py, sys; f = h5py.File(sys.argv[1]); "
                  "print(f['geometry'].shape, f['images'].shape, f['textures'].shape, f.attrs['format'])",
                  asset + "/dataset.h5"},
                 std::chrono::seconds(60));
  ASSERT_EQ(h5py.exit.exit_code, 0) << h5py.err;
  EXPECT_THAT(h5py.out, HasSubstr("(12, 32, 32, 3) (12, 2, 32, 32) (12, 32, 32, 7) fastage-asset-dataset-1"));
  // Beside each, the neutral frame's textures at full resolution (the truth's, 128 texels across): the same bytes.
  const auto neutral = FilesUnder(asset + "/dataset-neutral");
  EXPECT_EQ(neutral.size(), 3u);
  EXPECT_TRUE(FilesUnder(asset + "/batch-neutral") == neutral);
  EXPECT_TRUE(FilesUnder(asset + "/library-neutral") == neutral);

  // The training, tiny.
  const std::vector<std::string> tiny = {"--iterations",  "30", "--batch",        "4",  "--input-size",      "32",
                                         "--levels",      "3",  "--max-channels", "32", "--geometry-latent", "4",
                                         "--pose-latent", "3"};
  std::vector<std::string> argv = {
      "stage-process",           "asset", "train", "--dataset", asset + "/dataset.h5", "--output",
      asset + "/geometry-batch", "--json"};
  argv.insert(argv.end(), tiny.begin(), tiny.end());
  CommandResult train = RunCommand(argv, std::chrono::seconds(300));
  ASSERT_EQ(train.exit.exit_code, 0) << train.err;
  EXPECT_EQ(nlohmann::json::parse(train.out)["steps"], 30);
  processing::AssetTrainJob job;
  job.dataset = asset + "/dataset.h5";
  job.output_dir = asset + "/geometry-library";
  job.schedule.iterations = 30;
  job.schedule.batch = 4;
  job.geometry = {.input_size = 32, .levels = 3, .max_channels = 32, .geometry_latent = 4, .pose_latent = 3};
  ASSERT_TRUE(processing::TrainGeometryAsset(job).ok());
  v1::ProcessingJob train_request;
  train_request.set_stage(v1::PROCESSING_STAGE_ASSET_TRAIN);
  train_request.set_take_dir(take.path());
  v1::AssetOptions* a = train_request.mutable_asset();
  a->set_iterations(30);
  a->set_batch(4);
  a->set_input_size(32);
  a->set_levels(3);
  a->set_max_channels(32);
  a->set_geometry_latent(4);
  a->set_pose_latent(3);
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), train_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/geometry");
  // Torch's own archives (checkpoint-000030.pt, geometry_vae.pt) name the module's class with a counter of the modules
  // the process made before, so their bytes differ between processes; the TorchScript file holds the same weights and
  // is compared with the rest.
  auto without_archives = [](std::map<std::string, std::string> files) {
    EXPECT_EQ(files.erase("checkpoint-000030.pt") + files.erase("geometry_vae.pt"), 2u);
    return files;
  };
  const auto files = without_archives(FilesUnder(asset + "/geometry-batch"));
  EXPECT_EQ(files.size(), 5u);  // trainer.json, loss.csv and .png, the TorchScript net, evaluation.json
  for (const std::string other : {"geometry-library", "geometry"}) {
    const auto theirs = without_archives(FilesUnder(asset + "/" + other));
    ASSERT_EQ(theirs.size(), files.size()) << other;
    for (const auto& [name, bytes] : files) EXPECT_TRUE(theirs.at(name) == bytes) << name << " differs in " << other;
  }

  // The expression VAE (on both cameras' crops) and the mapping (from the worker's two VAEs), the same three ways.
  auto same_runs = [&](const std::string& name, const char* archive) {
    auto without = [&](std::map<std::string, std::string> run) {
      EXPECT_EQ(run.erase("checkpoint-000020.pt") + run.erase(archive), 2u) << name;
      return run;
    };
    const auto mine = without(FilesUnder(asset + "/" + name + "-batch"));
    // trainer.json, loss.csv and .png, evaluation.json; the mapping's picture of a frame driven (driven.png), the
    // texture VAE's TorchScript
    EXPECT_EQ(mine.size(), name == "mapping" || name == "finetune" || name == "texture" ? 5u : 4u) << name;
    for (const std::string& other : {name + "-library", name}) {
      const auto theirs = without(FilesUnder(asset + "/" + other));
      ASSERT_EQ(theirs.size(), mine.size()) << other;
      for (const auto& [file, bytes] : mine) EXPECT_TRUE(theirs.at(file) == bytes) << file << " differs in " << other;
    }
  };
  // The expression VAE's tiny net through the command line, into `output`, with `schedule`'s options.
  auto train_expression = [&](const std::string& output, const std::vector<std::string>& schedule) {
    std::vector<std::string> command = {"stage-process",
                                        "asset",
                                        "train",
                                        "--network",
                                        "expression",
                                        "--dataset",
                                        asset + "/dataset.h5",
                                        "--output",
                                        asset + "/" + output,
                                        "--input-size",
                                        "32",
                                        "--levels",
                                        "3",
                                        "--max-channels",
                                        "32",
                                        "--expression-latent",
                                        "4",
                                        "--view-latent",
                                        "2",
                                        "--json"};
    command.insert(command.end(), schedule.begin(), schedule.end());
    return RunCommand(command, std::chrono::seconds(300));
  };
  CommandResult expression = train_expression("expression-batch", {"--iterations", "20", "--batch", "4"});
  ASSERT_EQ(expression.exit.exit_code, 0) << expression.err;
  EXPECT_EQ(nlohmann::json::parse(expression.out)["trained_cameras"].size(), 2u);
  {
    // Each network's own default schedule where the command line gives none: the expression VAE's batch, not the
    // geometry VAE's the shared --batch is bound to.
    const int expression_batch = processing::ExpressionTrainJob{}.schedule.batch;
    ASSERT_NE(expression_batch, processing::AssetTrainJob{}.schedule.batch);
    CommandResult defaults = train_expression("expression-defaults", {"--iterations", "1"});
    ASSERT_EQ(defaults.exit.exit_code, 0) << defaults.err;
    const nlohmann::json trainer = nlohmann::json::parse(ReadFile(asset + "/expression-defaults/trainer.json"));
    EXPECT_EQ(trainer["options"]["batch"], expression_batch) << trainer.dump();
  }
  processing::ExpressionTrainJob expression_job;
  expression_job.dataset = asset + "/dataset.h5";
  expression_job.output_dir = asset + "/expression-library";
  expression_job.schedule.iterations = 20;
  expression_job.schedule.batch = 4;
  expression_job.expression = {
      .input_size = 32, .levels = 3, .max_channels = 32, .expression_latent = 4, .view_latent = 2};
  ASSERT_TRUE(processing::TrainExpressionAsset(expression_job).ok());
  v1::ProcessingJob expression_request = train_request;
  a = expression_request.mutable_asset();
  a->set_network(v1::ASSET_NETWORK_EXPRESSION);
  a->clear_geometry_latent();
  a->clear_pose_latent();
  a->set_iterations(20);
  a->set_expression_latent(4);
  a->set_view_latent(2);
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), expression_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/expression");
  same_runs("expression", "expression_vae.pt");

  CommandResult mapping = RunCommand({"stage-process", "asset", "train", "--network", "mapping", "--dataset",
                                      asset + "/dataset.h5", "--output", asset + "/mapping-batch", "--iterations", "20",
                                      "--batch", "8", "--hidden", "16", "--input-noise", "0.05", "--json"},
                                     std::chrono::seconds(300));
  ASSERT_EQ(mapping.exit.exit_code, 0) << mapping.err;
  const nlohmann::json driven = nlohmann::json::parse(mapping.out)["evaluation"];
  ASSERT_EQ(driven["cameras"].size(), 2u);
  EXPECT_EQ(driven["cameras"][0]["camera"], "mv-01");
  processing::MappingTrainJob mapping_job;
  mapping_job.dataset = asset + "/dataset.h5";
  mapping_job.output_dir = asset + "/mapping-library";
  mapping_job.schedule.iterations = 20;
  mapping_job.schedule.batch = 8;
  mapping_job.mapping.hidden = 16;
  mapping_job.input_noise = 0.05;
  ASSERT_TRUE(processing::TrainLatentMapping(mapping_job).ok());
  v1::ProcessingJob mapping_request;
  mapping_request.set_stage(v1::PROCESSING_STAGE_ASSET_TRAIN);
  mapping_request.set_take_dir(take.path());
  a = mapping_request.mutable_asset();
  a->set_network(v1::ASSET_NETWORK_MAPPING);
  a->set_iterations(20);
  a->set_batch(8);
  a->set_hidden(16);
  a->set_input_noise(0.05);
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), mapping_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/mapping");
  same_runs("mapping", "mapping.pt");
  CommandResult evaluated = RunCommand(
      {"stage-process", "asset", "evaluate", "--network", "mapping", "--dataset", asset + "/dataset.h5", "--json"},
      std::chrono::seconds(120));
  ASSERT_EQ(evaluated.exit.exit_code, 0) << evaluated.err;
  EXPECT_EQ(nlohmann::json::parse(evaluated.out), nlohmann::json::parse(ReadFile(asset + "/mapping/evaluation.json")));

  // The third stage (the driving path fine-tuned, from the worker's runs), the same three ways; inference below then
  // drives through the worker's.
  CommandResult finetune = RunCommand({"stage-process",
                                       "asset",
                                       "train",
                                       "--network",
                                       "finetune",
                                       "--dataset",
                                       asset + "/dataset.h5",
                                       "--output",
                                       asset + "/finetune-batch",
                                       "--iterations",
                                       "20",
                                       "--batch",
                                       "8",
                                       "--learning-rate",
                                       "2e-3",
                                       "--jitter-scale",
                                       "0.05",
                                       "--jitter-rotation",
                                       "3",
                                       "--jitter-shift",
                                       "0.04",
                                       "--jitter-gain",
                                       "0.2",
                                       "--jitter-noise",
                                       "0.02",
                                       "--json"},
                                      std::chrono::seconds(300));
  ASSERT_EQ(finetune.exit.exit_code, 0) << finetune.err;
  EXPECT_EQ(nlohmann::json::parse(finetune.out)["evaluation"]["cameras"].size(), 2u);
  processing::FineTuneJob finetune_job;
  finetune_job.dataset = asset + "/dataset.h5";
  finetune_job.output_dir = asset + "/finetune-library";
  finetune_job.schedule.iterations = 20;
  finetune_job.schedule.batch = 8;
  finetune_job.schedule.learning_rate = 2e-3;
  finetune_job.jitter_scale = 0.05;
  finetune_job.jitter_rotation_deg = 3;
  finetune_job.jitter_shift = 0.04;
  finetune_job.jitter_gain = 0.2;
  finetune_job.jitter_noise = 0.02;
  ASSERT_TRUE(processing::FineTuneDrivingAsset(finetune_job).ok());
  v1::ProcessingJob finetune_request = mapping_request;
  a = finetune_request.mutable_asset();
  a->set_network(v1::ASSET_NETWORK_FINETUNE);
  a->clear_hidden();
  a->clear_input_noise();
  a->set_learning_rate(2e-3);
  v1::CropJitter* jitter = a->mutable_jitter();
  jitter->set_scale(0.05);
  jitter->set_rotation_deg(3);
  jitter->set_shift(0.04);
  jitter->set_gain(0.2);
  jitter->set_noise(0.02);
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), finetune_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/finetune");
  same_runs("finetune", "driving_net.pt");

  // The texture VAE and the texture mapping (from the worker's geometry and texture runs; evaluated driven through the
  // worker's fine-tuned path), the same three ways; inference below then writes each frame's textures.
  const std::vector<std::string> tiny_texture = {"--iterations", "20", "--batch",        "4",  "--input-size",     "32",
                                                 "--levels",     "3",  "--max-channels", "32", "--texture-latent", "4"};
  argv = {"stage-process",
          "asset",
          "train",
          "--network",
          "texture",
          "--dataset",
          asset + "/dataset.h5",
          "--output",
          asset + "/texture-batch",
          "--json"};
  argv.insert(argv.end(), tiny_texture.begin(), tiny_texture.end());
  CommandResult texture = RunCommand(argv, std::chrono::seconds(300));
  ASSERT_EQ(texture.exit.exit_code, 0) << texture.err;
  EXPECT_EQ(nlohmann::json::parse(texture.out)["steps"], 20);
  processing::TextureTrainJob texture_job;
  texture_job.dataset = asset + "/dataset.h5";
  texture_job.output_dir = asset + "/texture-library";
  texture_job.schedule.iterations = 20;
  texture_job.schedule.batch = 4;
  texture_job.texture = {.input_size = 32, .levels = 3, .max_channels = 32, .texture_latent = 4};
  ASSERT_TRUE(processing::TrainTextureAsset(texture_job).ok());
  v1::ProcessingJob texture_request = train_request;
  a = texture_request.mutable_asset();
  a->set_network(v1::ASSET_NETWORK_TEXTURE);
  a->clear_geometry_latent();
  a->clear_pose_latent();
  a->set_iterations(20);
  a->set_texture_latent(4);
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), texture_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/texture");
  same_runs("texture", "texture_vae.pt");

  CommandResult texture_mapping = RunCommand(
      {"stage-process", "asset", "train", "--network", "texture-mapping", "--dataset", asset + "/dataset.h5",
       "--output", asset + "/texture_mapping-batch", "--iterations", "20", "--batch", "8", "--hidden", "16", "--json"},
      std::chrono::seconds(300));
  ASSERT_EQ(texture_mapping.exit.exit_code, 0) << texture_mapping.err;
  const nlohmann::json textures_driven = nlohmann::json::parse(texture_mapping.out)["evaluation"];
  EXPECT_EQ(textures_driven["driven_through"], "finetune");
  EXPECT_EQ(textures_driven["held_out_block"]["cameras"].size(), 2u);
  processing::TextureMappingJob texture_mapping_job;
  texture_mapping_job.dataset = asset + "/dataset.h5";
  texture_mapping_job.output_dir = asset + "/texture_mapping-library";
  texture_mapping_job.schedule.iterations = 20;
  texture_mapping_job.schedule.batch = 8;
  texture_mapping_job.mapping.hidden = 16;
  ASSERT_TRUE(processing::TrainTextureMapping(texture_mapping_job).ok());
  v1::ProcessingJob texture_mapping_request = mapping_request;
  texture_mapping_request.mutable_asset()->set_network(v1::ASSET_NETWORK_TEXTURE_MAPPING);
  texture_mapping_request.mutable_asset()->clear_input_noise();  // the mapping's 0.05; the default here
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), texture_mapping_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/texture_mapping");
  same_runs("texture_mapping", "texture_mapping.pt");
  CommandResult textures_evaluated = RunCommand({"stage-process", "asset", "evaluate", "--network", "texture-mapping",
                                                 "--dataset", asset + "/dataset.h5", "--json"},
                                                std::chrono::seconds(120));
  ASSERT_EQ(textures_evaluated.exit.exit_code, 0) << textures_evaluated.err;
  EXPECT_EQ(nlohmann::json::parse(textures_evaluated.out),
            nlohmann::json::parse(ReadFile(asset + "/texture_mapping/evaluation.json")));

  // The asset driven from mv-05's frames of the take, three ways: the same files; each frame's crop is the dataset's
  // own crop of that camera and frame, and the mesh opens in Open3D with the template's UVs.
  CommandResult infer = RunCommand({"stage-process", "asset", "infer", "--dataset", asset + "/dataset.h5", "--camera",
                                    "mv-05", "--take", take.path(), "--output", asset + "/infer-batch", "--json"},
                                   std::chrono::seconds(120));
  ASSERT_EQ(infer.exit.exit_code, 0) << infer.err;
  EXPECT_EQ(nlohmann::json::parse(infer.out)["frames"].size(), 12u);
  ASSERT_TRUE(processing::InferAsset({.dataset = asset + "/dataset.h5",
                                      .camera = "mv-05",
                                      .take_dir = take.path(),
                                      .output_dir = asset + "/infer-library"})
                  .ok());
  v1::ProcessingJob infer_request;
  infer_request.set_stage(v1::PROCESSING_STAGE_ASSET_INFER);
  infer_request.set_take_dir(take.path());
  infer_request.add_cameras("mv-05");
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), infer_request, &last));
  EXPECT_EQ(last.output_dir(), asset + "/infer/mv-05");
  const auto inferred = FilesUnder(asset + "/infer-batch");
  // crop.png, geometry_map.exr, mesh.obj, albedo.exr, specular.exr, normal_tangent.exr a frame; the twelve meshes as
  // one glTF animation; frames.json
  EXPECT_EQ(inferred.size(), 12u * 6 + 2);
  EXPECT_EQ(nlohmann::json::parse(infer.out)["textures"], true);
  // At the neutral textures' full resolution (the wrinkle maps of the 32-texel net added to them), as OpenImageIO
  // reads them.
  EXPECT_EQ(nlohmann::json::parse(infer.out)["texture_size"], 128);
  CommandResult oiio = RunCommand({"/usr/bin/oiiotool", "--info", asset + "/infer-batch/frame-000400/albedo.exr"},
                                  std::chrono::seconds(60));
  ASSERT_EQ(oiio.exit.exit_code, 0) << oiio.err;
  EXPECT_THAT(oiio.out, HasSubstr("128 x  128, 3 channel, float openexr"));
  EXPECT_EQ(nlohmann::json::parse(infer.out)["gltf"], nlohmann::json::array({"animation-000000.glb"}));
  for (const char* other : {"infer-library", "infer/mv-05"}) {
    const auto theirs = FilesUnder(asset + "/" + other);
    ASSERT_EQ(theirs.size(), inferred.size()) << other;
    for (const auto& [file, bytes] : inferred) EXPECT_TRUE(theirs.at(file) == bytes) << file << " differs in " << other;
  }
  CommandResult opened = RunCommand(
      {"/usr/bin/python3", "-c",
       "import h5py, numpy, open3d, sys\n"
       "d = h5py.File(sys.argv[1] + '/dataset.h5')\n"
       "i = list(d['frame'][:]).index(400)\n"
       "crop = numpy.asarray(open3d.io.read_image(sys.argv[1] + '/infer-batch/frame-000400/crop.png'))\n"
       "mesh = open3d.io.read_triangle_mesh(sys.argv[1] + '/infer-batch/frame-000400/mesh.obj')\n"
       "print(numpy.array_equal(crop, d['images'][i, 1]), len(mesh.vertices) > 1000, mesh.has_triangle_uvs())",
       asset},
      std::chrono::seconds(60));
  ASSERT_EQ(opened.exit.exit_code, 0) << opened.err;
  EXPECT_THAT(opened.out, HasSubstr("True True True"));
  // The glTF's third frame (400) is that frame's mesh: the rest (the template) moved by its morph target.
  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok());
  auto mesh = ReadObj(asset + "/infer-batch/frame-000400/mesh.obj");
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  const std::vector<Eigen::Vector3f> from_glb = GlbFrame(asset + "/infer-batch/animation-000000.glb", 2);
  ASSERT_EQ(from_glb.size(), mesh->positions.size());
  double worst = 0;
  for (size_t v = 0; v < from_glb.size(); ++v) {
    worst = std::max<double>(worst, (from_glb[v] - mesh->positions[v]).norm());
  }
  EXPECT_LT(worst, 1e-3) << "mm (the OBJ's 6 decimals)";
  // Its material: the neutral frame's textures at full resolution, a base colour and a normal map, as tinygltf
  // decodes them.
  {
    tinygltf::TinyGLTF loader;
    tinygltf::Model model;
    std::string error, warning;
    ASSERT_TRUE(loader.LoadBinaryFromFile(&model, &error, &warning, asset + "/infer-batch/animation-000000.glb"));
    ASSERT_EQ(model.materials.size(), 1u);
    EXPECT_EQ(model.meshes[0].primitives[0].material, 0);
    const tinygltf::Material& m = model.materials[0];
    ASSERT_EQ(model.images.size(), 2u);
    const tinygltf::Image& colour =
        model.images.at(model.textures.at(m.pbrMetallicRoughness.baseColorTexture.index).source);
    const tinygltf::Image& normal = model.images.at(model.textures.at(m.normalTexture.index).source);
    EXPECT_EQ(colour.width, 128);
    EXPECT_EQ(normal.height, 128);
    EXPECT_EQ(colour.mimeType, "image/png");
    // A skin texel's colour is the neutral albedo's, in sRGB.
    auto neutral_albedo = processing::ReadImageFile(asset + "/dataset-neutral/albedo.exr");
    ASSERT_TRUE(neutral_albedo.ok());
    const int x = 64, y = 64;
    ASSERT_EQ(neutral_albedo->at(x, y)[3], 1.f) << "texel (64, 64) is not skin";
    const double linear = neutral_albedo->at(x, y)[1];
    const double srgb = linear <= 0.0031308 ? 12.92 * linear : 1.055 * std::pow(linear, 1 / 2.4) - 0.055;
    EXPECT_NEAR(colour.image[(y * colour.width + x) * colour.component + 1], 255 * srgb, 1.0);
  }
  EXPECT_GT((mesh->positions[0] - face->mesh.positions[0]).norm(), 1e-3) << "the frame's mesh is not the rest's";
  CommandResult unknown = RunCommand({"stage-process", "asset", "infer", "--dataset", asset + "/dataset.h5", "--camera",
                                      "mv-09", "--take", take.path()},
                                     std::chrono::seconds(60));
  EXPECT_EQ(unknown.exit.exit_code, 2);
  EXPECT_THAT(unknown.err, HasSubstr("no crop of camera \"mv-09\" (it cropped: mv-01, mv-05)"));

  // A job's options the stage does not take are refused, naming them.
  v1::ProcessingJob wrong = request;
  wrong.set_stage(v1::PROCESSING_STAGE_PHOTOMETRIC);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(), HasSubstr("takes no asset options"));
  wrong = request;
  wrong.mutable_asset()->set_freeze_encoder(true);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(), HasSubstr("takes no training options"));
  wrong = train_request;
  wrong.set_first_frame(3);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(), HasSubstr("the asset's training takes no frames"));
  wrong = mapping_request;
  wrong.mutable_asset()->set_view_latent(3);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_MAPPING network's"));
  CommandResult misplaced = RunCommand({"stage-process", "asset", "train", "--network", "mapping", "--dataset",
                                        asset + "/dataset.h5", "--pose-latent", "2"},
                                       std::chrono::seconds(60));
  EXPECT_EQ(misplaced.exit.exit_code, 2);
  EXPECT_THAT(misplaced.err, HasSubstr("--pose-latent is not an option of the mapping network"));
  wrong = mapping_request;
  wrong.mutable_asset()->set_direct_textures(true);  // the texture VAE's ablation
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_MAPPING network's"));
  wrong = request;
  wrong.mutable_asset()->set_neutral_texture_size(64);  // the dataset's option, not a training one
  wrong.set_stage(v1::PROCESSING_STAGE_ASSET_TRAIN);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(), HasSubstr("the asset's training takes no frames"));
  wrong = finetune_request;
  wrong.mutable_asset()->set_hidden(8);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_FINETUNE network's"));
  wrong = mapping_request;
  wrong.mutable_asset()->mutable_jitter()->set_scale(0.1);  // the fine-tuning's
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_MAPPING network's"));
  wrong = finetune_request;
  wrong.mutable_asset()->set_input_noise(0.1);  // the mappings'
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_FINETUNE network's"));
  wrong = request;
  wrong.mutable_asset()->set_learning_rate(1e-3);  // the training's, not the dataset's
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(), HasSubstr("takes no training options"));
  wrong = train_request;
  wrong.mutable_asset()->set_crop_mm(250);  // the dataset's, not the training's
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(), HasSubstr("the asset's training takes no frames"));
  wrong = mapping_request;
  wrong.mutable_asset()->set_map_loss(10);  // the fine-tuning's
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_MAPPING network's"));
  wrong = finetune_request;
  wrong.mutable_asset()->set_region_weight(5);  // the geometry VAE's
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("not one of the ASSET_NETWORK_FINETUNE network's"));
  wrong = finetune_request;
  wrong.mutable_asset()->set_map_loss(0.5);
  EXPECT_THAT(RunOnWorkerStatus(take.path(), wrong).error_message(),
              HasSubstr("map loss region weight 0.5 is neither 0 nor in 1..1000"));
  // A worker's job takes its network's default schedule where the job gives none: the expression VAE's batch (its
  // worker run, which nothing after this reads, trained again for one step).
  v1::ProcessingJob defaults_request = expression_request;
  defaults_request.mutable_asset()->set_iterations(1);
  defaults_request.mutable_asset()->clear_batch();
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), defaults_request, &last));
  EXPECT_EQ(nlohmann::json::parse(ReadFile(asset + "/expression/trainer.json"))["options"]["batch"],
            processing::ExpressionTrainJob{}.schedule.batch);
  // The dataset's frame step and split through the worker's job as through the library (last: it replaces the
  // dataset the runs above read).
  processing::DatasetOptions split = options;
  split.output = asset + "/split-library.h5";
  split.frame_step = 2;
  split.held_out_fraction = 0.25;
  split.held_out_blocks = 2;
  split.held_out_sequence = "none";
  auto split_library = processing::BuildAssetDataset(split);
  ASSERT_TRUE(split_library.ok()) << split_library.status();
  EXPECT_EQ(split_library->frames, 6);
  v1::ProcessingJob split_request = request;
  split_request.mutable_asset()->set_frame_step(2);
  split_request.mutable_asset()->set_held_out_fraction(0.25);
  split_request.mutable_asset()->set_held_out_blocks(2);
  split_request.mutable_asset()->set_held_out_sequence("none");
  ASSERT_NO_FATAL_FAILURE(RunOnWorker(take.path(), split_request, &last));
  EXPECT_TRUE(ReadFile(asset + "/dataset.h5") == ReadFile(asset + "/split-library.h5"));
  CommandResult missing =
      RunCommand({"stage-process", "asset", "train", "--dataset", asset + "/none.h5"}, std::chrono::seconds(60));
  EXPECT_EQ(missing.exit.exit_code, 2);
  EXPECT_THAT(missing.err, HasSubstr("none.h5: no such file"));
}

}  // namespace
}  // namespace stage::testing
