// A driven mesh sequence written as glTF (stage/processing/mesh_sequence.h) imported by Blender, headless: the
// template's topology and UVs, a shape key per frame, and the animation passing through every frame's positions at
// one frame's spacing.
#include "stage/processing/mesh_sequence.h"

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "stage/common/subprocess.h"
#include "stage/processing/face_template.h"
#include "test_support.h"

namespace stage::testing {
namespace {

// Prints RESULT {json}: the mesh's counts, each shape key's name and the scene frame where its weight peaks, and
// per frame there the largest distance from an expected vertex (argv[-1]: float32 frames x vertices x 3, Blender's
// axes, metres) to the evaluated mesh's nearest vertex.
constexpr char kBlenderScript[] = R"(
import bpy, json, sys, struct
from mathutils import kdtree, Vector
bpy.ops.wm.read_factory_settings(use_empty=True)
# Debian 12's Blender 3.4 fails with its default shading option ('NORMALS': np.bool, gone from numpy 1.24)
bpy.ops.import_scene.gltf(filepath=sys.argv[-2], import_shading='SMOOTH')
obj = [o for o in bpy.context.scene.objects if o.type == 'MESH'][0]
me = obj.data
keys = me.shape_keys.key_blocks
peaks = {}
for fc in me.shape_keys.animation_data.action.fcurves:
    name = fc.data_path.split('"')[1]
    peaks[name] = max(fc.keyframe_points, key=lambda p: p.co[1]).co[0]
names = [k.name for k in keys][1:]
raw = open(sys.argv[-1], 'rb').read()
n = len(me.vertices)
values = struct.unpack('%df' % (len(raw) // 4), raw)
worst = []
for f, name in enumerate(names):
    bpy.context.scene.frame_set(int(round(peaks[name])))
    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    tree = kdtree.KDTree(len(mesh.vertices))
    for i, v in enumerate(mesh.vertices):
        tree.insert(v.co, i)
    tree.balance()
    base = 3 * n * f
    worst.append(max(tree.find(Vector(values[base + 3 * i:base + 3 * i + 3]))[2] for i in range(n)))
    obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh_clear()
nodes = obj.active_material.node_tree.nodes if obj.active_material else []
images = sorted(list(t.image.size) for t in nodes if t.type == 'TEX_IMAGE' and t.image)
print("RESULT " + json.dumps({"vertices": n, "polygons": len(me.polygons), "uv_layers": len(me.uv_layers),
                              "names": names, "peaks": [peaks[k] for k in names], "worst_m": worst,
                              "materials": len(me.materials), "images": images,
                              "normal_maps": len([t for t in nodes if t.type == 'NORMAL_MAP'])}))
)";

TEST(MeshSequenceBlenderTest, BlenderImportsEveryFrameAsAShapeKeyOnTheAnimation) {
  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok()) << face.status();
  const TriangleMesh& rest = face->mesh;
  std::vector<processing::MeshSequenceFrame> frames;
  for (int k = 0; k < 4; ++k) {
    processing::MeshSequenceFrame f{.frame = 100 + 3 * k, .positions = rest.positions};
    for (Eigen::Vector3f& p : f.positions) {  // a jaw-like drop and a sideways wave, up to a few mm
      p += Eigen::Vector3f(1.5f * std::sin(0.9f * k + p.y() / 40), -2.0f * k * (p.y() < 0), 0.7f * k);
    }
    frames.push_back(std::move(f));
  }
  TempDir dir;
  const std::string glb = dir.path() + "/sequence.glb";
  // A material of a 4 x 2 base colour and a 2 x 2 flat normal map (PNG files' bytes).
  const std::string colour(
      "\x89\x50\x4e\x47\x0d\x0a\x1a\x0a\x00\x00\x00\x0d\x49\x48\x44\x52\x00\x00\x00\x04\x00\x00\x00\x02\x08\x02\x00"
      "\x00\x00\xf0\xca\xea\x34\x00\x00\x00\x10\x49\x44\x41\x54\x78\xda\x63\x38\x31\xad\x02\x8e\x18\x90\x39\x00\xc1"
      "\x8a\x0e\xb1\xd0\xc1\xce\xb9\x00\x00\x00\x00\x49\x45\x4e\x44\xae\x42\x60\x82",
      73);
  const std::string normal(
      "\x89\x50\x4e\x47\x0d\x0a\x1a\x0a\x00\x00\x00\x0d\x49\x48\x44\x52\x00\x00\x00\x02\x00\x00\x00\x02\x08\x02\x00"
      "\x00\x00\xfd\xd4\x9a\x73\x00\x00\x00\x10\x49\x44\x41\x54\x78\xda\x63\x68\x68\xf8\x0f\x44\x0c\x10\x0a\x00\x35"
      "\xf6\x07\xfd\xa1\x29\xec\x43\x00\x00\x00\x00\x49\x45\x4e\x44\xae\x42\x60\x82",
      73);
  ASSERT_TRUE(processing::WriteMeshSequenceGlb(
                  glb, rest, frames, {.frames_per_second = 24, .base_color_png = colour, .normal_png = normal})
                  .ok());
  // The expected positions in Blender's axes (glTF's +y up becomes +z; its +z, -y) and metres.
  std::vector<float> expected;
  for (const auto& f : frames) {
    for (const Eigen::Vector3f& p : f.positions) {
      expected.insert(expected.end(), {p.x() / 1000, -p.z() / 1000, p.y() / 1000});
    }
  }
  const std::string expected_path = dir.path() + "/expected.f32";
  std::ofstream(expected_path, std::ios::binary)
      .write(reinterpret_cast<const char*>(expected.data()), static_cast<std::streamsize>(4 * expected.size()));

  CommandResult blender = RunCommand(
      {"/usr/bin/blender", "-b", "--factory-startup", "--python-expr", kBlenderScript, "--", glb, expected_path},
      std::chrono::seconds(600));
  ASSERT_EQ(blender.exit.exit_code, 0) << blender.err << blender.out;
  const size_t at = blender.out.find("RESULT ");
  ASSERT_NE(at, std::string::npos) << blender.out << blender.err;
  const nlohmann::json r = nlohmann::json::parse(blender.out.substr(at + 7, blender.out.find('\n', at) - at - 7));
  std::printf("Blender: vertices %d, polygons %d, keys %s at frames %s, worst distance per frame (m) %s\n",
              r["vertices"].get<int>(), r["polygons"].get<int>(), r["names"].dump().c_str(), r["peaks"].dump().c_str(),
              r["worst_m"].dump().c_str());
  EXPECT_EQ(r["vertices"], rest.positions.size());
  EXPECT_EQ(r["polygons"], rest.triangles.size());
  EXPECT_EQ(r["uv_layers"], 1);
  EXPECT_EQ(r["materials"], 1);
  EXPECT_EQ(r["images"], nlohmann::json::array({{2, 2}, {4, 2}}));
  EXPECT_EQ(r["normal_maps"], 1);
  EXPECT_EQ(r["names"], nlohmann::json::array({"frame-000100", "frame-000103", "frame-000106", "frame-000109"}));
  ASSERT_EQ(r["peaks"].size(), 4u);
  for (size_t k = 1; k < 4; ++k) {  // 24 frames a second in the file, Blender's default scene rate
    EXPECT_NEAR(r["peaks"][k].get<double>() - r["peaks"][k - 1].get<double>(), 1.0, 1e-4) << k;
  }
  ASSERT_EQ(r["worst_m"].size(), 4u);
  for (size_t k = 0; k < 4; ++k) {
    EXPECT_LT(r["worst_m"][k].get<double>(), 1e-6) << "frame " << k << " (1 um: the floats' rounding)";
  }
}

TEST(MeshSequenceTest, RefusesAFrameWhoseVertexCountIsNotTheMeshs) {
  auto face = processing::ShippedFaceTemplate();
  ASSERT_TRUE(face.ok()) << face.status();
  TempDir dir;
  std::vector<processing::MeshSequenceFrame> frames = {{.frame = 7, .positions = {Eigen::Vector3f::Zero()}}};
  const absl::Status s = processing::WriteMeshSequenceGlb(dir.path() + "/x.glb", face->mesh, frames);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("frame 7 has 1 vertices"), std::string::npos) << s;
  EXPECT_EQ(processing::WriteMeshSequenceGlb(dir.path() + "/y.glb", face->mesh, {}).code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace stage::testing
