#include "stage/processing/mesh_sequence.h"

#include <tiny_gltf.h>

#include <cstring>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"

namespace stage::processing {
namespace {

constexpr double kMetresPerMm = 1e-3;

// The file's one buffer, grown section by section; each section a buffer view (4-byte aligned: every component here
// is 4 bytes).
class BufferBuilder {
 public:
  explicit BufferBuilder(tinygltf::Model* model) : model_(model) { model_->buffers.emplace_back(); }

  // A view of `bytes` bytes of `data`; `target` 0 for animation data.
  int AddView(const void* data, size_t bytes, int target) {
    std::vector<unsigned char>& buffer = model_->buffers[0].data;
    buffer.resize((buffer.size() + 3) / 4 * 4);  // after an image of any length
    tinygltf::BufferView view;
    view.buffer = 0;
    view.byteOffset = buffer.size();
    view.byteLength = bytes;
    view.target = target;
    buffer.resize(buffer.size() + bytes);
    std::memcpy(buffer.data() + view.byteOffset, data, bytes);
    model_->bufferViews.push_back(view);
    return static_cast<int>(model_->bufferViews.size()) - 1;
  }

  // An accessor of `count` elements of `type` (TINYGLTF_TYPE_*) at `offset` bytes into view `view`.
  int AddAccessor(int view, size_t offset, size_t count, int component, int type) {
    tinygltf::Accessor accessor;
    accessor.bufferView = view;
    accessor.byteOffset = offset;
    accessor.count = count;
    accessor.componentType = component;
    accessor.type = type;
    model_->accessors.push_back(accessor);
    return static_cast<int>(model_->accessors.size()) - 1;
  }

  // A float accessor with its bounds (glTF requires them for positions and for animation inputs).
  int AddBounded(int view, size_t offset, const float* values, size_t count, int type, int width) {
    const int index = AddAccessor(view, offset, count, TINYGLTF_COMPONENT_TYPE_FLOAT, type);
    tinygltf::Accessor& accessor = model_->accessors[index];
    accessor.minValues.assign(width, count == 0 ? 0 : 1e300);
    accessor.maxValues.assign(width, count == 0 ? 0 : -1e300);
    for (size_t i = 0; i < count; ++i) {
      for (int c = 0; c < width; ++c) {
        accessor.minValues[c] = std::min<double>(accessor.minValues[c], values[i * width + c]);
        accessor.maxValues[c] = std::max<double>(accessor.maxValues[c], values[i * width + c]);
      }
    }
    return index;
  }

 private:
  tinygltf::Model* model_;
};

std::vector<float> Metres(const std::vector<Eigen::Vector3f>& positions, const std::vector<Eigen::Vector3f>* less) {
  std::vector<float> out(3 * positions.size());
  for (size_t v = 0; v < positions.size(); ++v) {
    const Eigen::Vector3f p = less == nullptr ? positions[v] : Eigen::Vector3f(positions[v] - (*less)[v]);
    for (int c = 0; c < 3; ++c) out[3 * v + c] = static_cast<float>(p[c] * kMetresPerMm);
  }
  return out;
}

// The mesh: rest positions, uvs and triangles, and a morph target per frame.
tinygltf::Mesh BuildMesh(BufferBuilder& b, const TriangleMesh& rest, const std::vector<MeshSequenceFrame>& frames) {
  const size_t n = rest.positions.size();
  tinygltf::Primitive primitive;
  primitive.mode = TINYGLTF_MODE_TRIANGLES;
  std::vector<uint32_t> indices;
  indices.reserve(3 * rest.triangles.size());
  for (const auto& t : rest.triangles) indices.insert(indices.end(), t.begin(), t.end());
  primitive.indices = b.AddAccessor(b.AddView(indices.data(), 4 * indices.size(), TINYGLTF_TARGET_ELEMENT_ARRAY_BUFFER),
                                    0, indices.size(), TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT, TINYGLTF_TYPE_SCALAR);
  const std::vector<float> positions = Metres(rest.positions, nullptr);
  primitive.attributes["POSITION"] =
      b.AddBounded(b.AddView(positions.data(), 4 * positions.size(), TINYGLTF_TARGET_ARRAY_BUFFER), 0, positions.data(),
                   n, TINYGLTF_TYPE_VEC3, 3);
  // The rest's smooth (area-weighted) vertex normals: without them viewers shade the mesh flat, and a normal map is
  // made for the smooth surface. The targets carry none: the frames' normals are the rest's.
  std::vector<float> normals;
  normals.reserve(3 * n);
  for (const Eigen::Vector3f& v : rest.VertexNormals()) normals.insert(normals.end(), {v.x(), v.y(), v.z()});
  primitive.attributes["NORMAL"] =
      b.AddAccessor(b.AddView(normals.data(), 4 * normals.size(), TINYGLTF_TARGET_ARRAY_BUFFER), 0, n,
                    TINYGLTF_COMPONENT_TYPE_FLOAT, TINYGLTF_TYPE_VEC3);
  if (rest.uvs.size() == n) {
    std::vector<float> uvs(2 * n);
    for (size_t v = 0; v < n; ++v) {
      uvs[2 * v] = rest.uvs[v].x();
      uvs[2 * v + 1] = 1.0f - rest.uvs[v].y();
    }
    primitive.attributes["TEXCOORD_0"] =
        b.AddAccessor(b.AddView(uvs.data(), 4 * uvs.size(), TINYGLTF_TARGET_ARRAY_BUFFER), 0, n,
                      TINYGLTF_COMPONENT_TYPE_FLOAT, TINYGLTF_TYPE_VEC2);
  }
  std::vector<float> offsets;
  offsets.reserve(3 * n * frames.size());
  for (const MeshSequenceFrame& f : frames) {
    const std::vector<float> d = Metres(f.positions, &rest.positions);
    offsets.insert(offsets.end(), d.begin(), d.end());
  }
  const int view = b.AddView(offsets.data(), 4 * offsets.size(), TINYGLTF_TARGET_ARRAY_BUFFER);
  tinygltf::Value::Array names;
  tinygltf::Mesh mesh;
  mesh.name = "face";
  for (size_t k = 0; k < frames.size(); ++k) {
    const size_t at = 3 * n * k;
    primitive.targets.push_back(
        {{"POSITION", b.AddBounded(view, 4 * at, offsets.data() + at, n, TINYGLTF_TYPE_VEC3, 3)}});
    names.emplace_back(absl::StrFormat("frame-%06d", frames[k].frame));
  }
  mesh.primitives.push_back(primitive);
  mesh.weights.assign(frames.size(), 0.0);
  tinygltf::Value::Object extras;
  extras["targetNames"] = tinygltf::Value(names);
  mesh.extras = tinygltf::Value(extras);
  return mesh;
}

// The weights' animation: at key k, target k alone at 1.
tinygltf::Animation BuildAnimation(BufferBuilder& b, size_t keys, double frames_per_second) {
  std::vector<float> times(keys), weights(keys * keys, 0.0f);
  for (size_t k = 0; k < keys; ++k) {
    times[k] = static_cast<float>(k / frames_per_second);
    weights[k * keys + k] = 1.0f;
  }
  tinygltf::AnimationSampler sampler;
  sampler.input =
      b.AddBounded(b.AddView(times.data(), 4 * times.size(), 0), 0, times.data(), keys, TINYGLTF_TYPE_SCALAR, 1);
  sampler.output = b.AddAccessor(b.AddView(weights.data(), 4 * weights.size(), 0), 0, weights.size(),
                                 TINYGLTF_COMPONENT_TYPE_FLOAT, TINYGLTF_TYPE_SCALAR);
  sampler.interpolation = "LINEAR";
  tinygltf::AnimationChannel channel;
  channel.sampler = 0;
  channel.target_node = 0;
  channel.target_path = "weights";
  tinygltf::Animation animation;
  animation.name = "driven";
  animation.samplers.push_back(sampler);
  animation.channels.push_back(channel);
  return animation;
}

// The material of the options' textures (the mesh's only): an image per PNG in the buffer, a texture of each.
void AddMaterial(BufferBuilder& b, const MeshSequenceOptions& options, tinygltf::Model* model) {
  auto texture = [&](const std::string& png, const char* name) {
    tinygltf::Image image;
    image.name = name;
    image.mimeType = "image/png";
    image.bufferView = b.AddView(png.data(), png.size(), 0);
    model->images.push_back(image);
    tinygltf::Texture t;
    t.source = static_cast<int>(model->images.size()) - 1;
    t.sampler = 0;
    model->textures.push_back(t);
    return static_cast<int>(model->textures.size()) - 1;
  };
  tinygltf::Sampler sampler;
  sampler.magFilter = TINYGLTF_TEXTURE_FILTER_LINEAR;
  sampler.minFilter = TINYGLTF_TEXTURE_FILTER_LINEAR_MIPMAP_LINEAR;
  model->samplers.push_back(sampler);
  tinygltf::Material material;
  material.name = "skin";
  material.pbrMetallicRoughness.baseColorTexture.index = texture(options.base_color_png, "base_color");
  material.pbrMetallicRoughness.metallicFactor = 0;
  material.pbrMetallicRoughness.roughnessFactor = 0.5;
  if (!options.normal_png.empty()) material.normalTexture.index = texture(options.normal_png, "normal");
  model->materials.push_back(material);
}

}  // namespace

absl::Status MeshSequenceOptions::Validate() const {
  if (!(frames_per_second > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("mesh sequence: frames_per_second ", frames_per_second));
  }
  if (base_color_png.empty() && !normal_png.empty()) {
    return absl::InvalidArgumentError("mesh sequence: a normal map without a base colour");
  }
  return absl::OkStatus();
}

absl::Status WriteMeshSequenceGlb(const std::string& path, const TriangleMesh& rest,
                                  const std::vector<MeshSequenceFrame>& frames, const MeshSequenceOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (frames.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": a mesh sequence of no frames"));
  for (const MeshSequenceFrame& f : frames) {
    if (f.positions.size() != rest.positions.size()) {
      return absl::InvalidArgumentError(absl::StrFormat("%s: frame %d has %d vertices, the mesh %d", path, f.frame,
                                                        f.positions.size(), rest.positions.size()));
    }
  }
  tinygltf::Model model;
  model.asset.version = "2.0";
  model.asset.generator = options.generator.empty() ? "FaStage" : options.generator;
  BufferBuilder b(&model);
  model.meshes.push_back(BuildMesh(b, rest, frames));
  if (!options.base_color_png.empty()) {
    AddMaterial(b, options, &model);
    model.meshes[0].primitives[0].material = 0;
  }
  tinygltf::Node node;
  node.name = "face";
  node.mesh = 0;
  model.nodes.push_back(node);
  tinygltf::Scene scene;
  scene.nodes = {0};
  model.scenes.push_back(scene);
  model.defaultScene = 0;
  model.animations.push_back(BuildAnimation(b, frames.size(), options.frames_per_second));
  model.buffers[0].data.resize((model.buffers[0].data.size() + 3) / 4 * 4);  // the GLB chunk's alignment
  std::ostringstream out;
  tinygltf::TinyGLTF writer;
  if (!writer.WriteGltfSceneToStream(&model, out, /*prettyPrint=*/false, /*writeBinary=*/true)) {
    return absl::InternalError(absl::StrCat(path, ": tinygltf could not write the sequence"));
  }
  return WriteFileAtomically(path, out.str());
}

}  // namespace stage::processing
