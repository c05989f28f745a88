// A neural asset's dataset: see asset_dataset.h.
#include "stage/processing/asset_dataset.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/status.h"
#include "stage/processing/face_template.h"
#include "stage/processing/light_model.h"
#include "stage/processing/map_files.h"
#include "stage/processing/photometric_stage.h"
#include "stage/processing/take_frames.h"
#include "stage/processing/texture_fusion.h"
#include "stage/processing/uv_geometry.h"
#include "stage/storage/array_file.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;
using storage::ArrayType;

constexpr const char* kFormat = "fastage-asset-dataset-1";

// The frames under `root` (frame-NNNNNN directories) in [first, last) that hold `file`, in order.
std::vector<int64_t> ListFrames(const std::string& root, const std::string& file, int64_t first, int64_t last) {
  std::vector<int64_t> frames;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(root, ec)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("frame-", 0) != 0 || name.size() != 12) continue;
    int64_t f = 0;
    try {
      f = std::stoll(name.substr(6));
    } catch (const std::exception&) {
      continue;
    }
    if (f < first || (last >= 0 && f >= last) || !fs::exists(entry.path() / file)) continue;
    frames.push_back(f);
  }
  std::sort(frames.begin(), frames.end());
  return frames;
}

// The texel centre (row, col) of a square map of `size` in its UV layout (row 0 at v = 1).
Eigen::Vector2f TexelUv(int row, int col, int size) {
  return {(static_cast<float>(col) + 0.5f) / static_cast<float>(size),
          1.0f - (static_cast<float>(row) + 0.5f) / static_cast<float>(size)};
}

// One of the simulator's RGBA UV maps (uv_position, uv_albedo, ...: alpha 1 where covered) at `uv` of its layout,
// its first three channels interpolated between the four nearest texel centres; false where one of them is not
// covered.
bool SampleTruthMap(const Image& map, const Eigen::Vector2f& uv, Eigen::Vector3f* out) {
  const float x = uv.x() * static_cast<float>(map.width) - 0.5f,
              y = (1 - uv.y()) * static_cast<float>(map.height) - 0.5f;
  const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
  if (x0 < 0 || y0 < 0 || x0 + 1 >= map.width || y0 + 1 >= map.height) return false;
  const float fx = x - static_cast<float>(x0), fy = y - static_cast<float>(y0);
  Eigen::Vector3f p = Eigen::Vector3f::Zero();
  for (int dy = 0; dy < 2; ++dy) {
    for (int dx = 0; dx < 2; ++dx) {
      const float* texel = &map.pixels[(static_cast<size_t>(y0 + dy) * map.width + x0 + dx) * 4];
      if (texel[3] < 1) return false;
      const float w = (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy);
      p += w * Eigen::Vector3f(texel[0], texel[1], texel[2]);
    }
  }
  *out = p;
  return true;
}

struct FrameGeometry {
  std::vector<float> points;   // size x size x 3, head frame, mm
  std::vector<uint8_t> valid;  // size x size
  Eigen::Matrix4f stage_from_head = Eigen::Matrix4f::Identity();
};

// A frame's map of `size` texels: each texel's head-frame point from `point` (nullopt: not valid), the pose from
// `head_from_stage`.
FrameGeometry DrawFrame(int size, const Eigen::Isometry3f& head_from_stage,
                        const std::function<std::optional<Eigen::Vector3f>(int row, int col)>& point) {
  FrameGeometry g;
  g.points.assign(static_cast<size_t>(size) * size * 3, 0.f);
  g.valid.assign(static_cast<size_t>(size) * size, 0);
  g.stage_from_head = head_from_stage.inverse().matrix();
  for (int row = 0; row < size; ++row) {
    for (int col = 0; col < size; ++col) {
      const std::optional<Eigen::Vector3f> p = point(row, col);
      if (!p) continue;
      const size_t t = static_cast<size_t>(row) * size + col;
      std::copy(p->data(), p->data() + 3, &g.points[3 * t]);
      g.valid[t] = 1;
    }
  }
  return g;
}

// The truth's surface in frame `frame_dir` drawn into the template's layout: each texel the template's layout covers
// (`layout`) takes the truth's point at its place in the head's layout, moved into the head's frame.
absl::StatusOr<FrameGeometry> TruthGeometry(const FaceTemplate& face, const std::vector<uint8_t>& layout, int size,
                                            const std::string& frame_dir) {
  const std::string path = frame_dir + "/uv_position.exr";
  STAGE_ASSIGN_OR_RETURN(const Image map, ReadImageFile(path));
  if (map.channels != 4) return absl::InvalidArgumentError(absl::StrCat(path, ": not an RGBA position map"));
  STAGE_ASSIGN_OR_RETURN(const Eigen::Isometry3f head_from_stage, HeadFromStage(frame_dir + "/pose.json"));
  return DrawFrame(size, head_from_stage, [&](int row, int col) -> std::optional<Eigen::Vector3f> {
    Eigen::Vector3f p;
    if (!layout[static_cast<size_t>(row) * size + col] ||
        !SampleTruthMap(map, face.HeadLayoutUv(TexelUv(row, col, size)), &p)) {
      return std::nullopt;
    }
    return head_from_stage * p;
  });
}

// The fit's geometry map of frame `frame_dir` (already in the head's frame), resampled to `size` when it has another.
absl::StatusOr<FrameGeometry> FitGeometry(int size, const std::string& frame_dir) {
  STAGE_ASSIGN_OR_RETURN(const GeometryMap map, ReadGeometryMap(frame_dir + "/geometry_map.exr"));
  STAGE_ASSIGN_OR_RETURN(const Eigen::Isometry3f head_from_stage, HeadFromStage(frame_dir + "/pose.json"));
  return DrawFrame(size, head_from_stage, [&](int row, int col) -> std::optional<Eigen::Vector3f> {
    if (map.size != size) return SampleGeometryMap(map, TexelUv(row, col, size));
    const size_t t = static_cast<size_t>(row) * size + col;
    if (map.state[t] == TexelState::kEmpty) return std::nullopt;
    return map.points[t];
  });
}

// A frame's textures in the template's layout: size x size x kTextureChannels (linear albedo RGB, specular intensity,
// the tangent-space normal), and where they hold the skin.
struct FrameTextures {
  std::vector<float> maps;
  std::vector<uint8_t> valid;
};

// Head-frame normals (channels 4..6 of `maps`) turned into tangent space, over the frame's geometry at the textures'
// size (`points`, head frame, mm): per texel the tangent is the surface's direction of increasing u, made orthogonal
// to its normal, the bitangent the normal x tangent towards increasing v (+y is +v, OpenGL's convention, as
// texture fusion writes them: docs/assets.md#texture-fusion); finite differences of the map, one-sided at its edge.
// A texel without a neighbour each way is not valid.
void NormalsToTangentSpace(const std::vector<float>& points, int size, FrameTextures* t) {
  auto at = [&](int r, int c) {
    return Eigen::Map<const Eigen::Vector3f>(&points[3 * (static_cast<size_t>(r) * size + c)]);
  };
  auto ok = [&](int r, int c) {
    return r >= 0 && c >= 0 && r < size && c < size && t->valid[static_cast<size_t>(r) * size + c];
  };
  std::vector<uint8_t> valid = t->valid;
  for (int r = 0; r < size; ++r) {
    for (int c = 0; c < size; ++c) {
      const size_t i = static_cast<size_t>(r) * size + c;
      if (!t->valid[i]) continue;
      const int c0 = ok(r, c - 1) ? c - 1 : c, c1 = ok(r, c + 1) ? c + 1 : c;
      const int r0 = ok(r + 1, c) ? r + 1 : r, r1 = ok(r - 1, c) ? r - 1 : r;  // v rises as the row falls
      float* m = &t->maps[kTextureChannels * i];
      if (c0 == c1 || r0 == r1) {
        valid[i] = 0;
        std::fill(m, m + kTextureChannels, 0.f);
        continue;
      }
      const Eigen::Vector3f du = at(r, c1) - at(r, c0), dv = at(r1, c) - at(r0, c);
      const Eigen::Vector3f n(m[4], m[5], m[6]);
      Eigen::Vector3f normal = du.cross(dv).normalized();
      if (normal.dot(n) < 0) normal = -normal;
      const Eigen::Vector3f tangent = (du - normal * normal.dot(du)).normalized();
      Eigen::Vector3f bitangent = normal.cross(tangent);
      if (bitangent.dot(dv) < 0) bitangent = -bitangent;
      m[4] = n.dot(tangent);
      m[5] = n.dot(bitangent);
      m[6] = n.dot(normal);
    }
  }
  t->valid = std::move(valid);
}

// The truth's textures of frame `frame_dir` drawn into the template's layout as TruthGeometry draws its surface:
// uv_albedo, uv_material's specular intensity and uv_normal (head frame) at each texel's place in the head's layout,
// the normals then in tangent space over the truth's own surface.
absl::StatusOr<FrameTextures> TruthTextures(const FaceTemplate& face, const std::vector<uint8_t>& layout, int size,
                                            const std::string& frame_dir) {
  STAGE_ASSIGN_OR_RETURN(const FrameGeometry g, TruthGeometry(face, layout, size, frame_dir));
  std::vector<Image> maps;
  for (const char* name : {"uv_albedo.exr", "uv_material.exr", "uv_normal.exr"}) {
    const std::string path = frame_dir + "/" + name;
    STAGE_ASSIGN_OR_RETURN(Image map, ReadImageFile(path));
    if (map.channels != 4) return absl::InvalidArgumentError(absl::StrCat(path, ": not an RGBA UV map"));
    maps.push_back(std::move(map));
  }
  FrameTextures t;
  t.maps.assign(static_cast<size_t>(size) * size * kTextureChannels, 0.f);
  t.valid.assign(static_cast<size_t>(size) * size, 0);
  for (int row = 0; row < size; ++row) {
    for (int col = 0; col < size; ++col) {
      const size_t i = static_cast<size_t>(row) * size + col;
      if (!g.valid[i]) continue;
      const Eigen::Vector2f uv = face.HeadLayoutUv(TexelUv(row, col, size));
      Eigen::Vector3f albedo, material, normal;
      if (!SampleTruthMap(maps[0], uv, &albedo) || !SampleTruthMap(maps[1], uv, &material) ||
          !SampleTruthMap(maps[2], uv, &normal) || normal.squaredNorm() == 0) {
        continue;
      }
      normal.normalize();
      float* m = &t.maps[kTextureChannels * i];
      std::copy(albedo.data(), albedo.data() + 3, m);
      m[3] = material.x();
      std::copy(normal.data(), normal.data() + 3, m + 4);
      t.valid[i] = 1;
    }
  }
  NormalsToTangentSpace(g.points, size, &t);
  return t;
}

// One of texture fusion's maps at `size` texels across: averaged down (or bilinear up) from the size it was fused at.
cv::Mat ResizedMap(const Image& image, int size) {
  cv::Mat m(image.height, image.width, CV_32FC(image.channels), const_cast<float*>(image.pixels.data()));
  if (image.width == size) return m.clone();
  cv::Mat out;
  cv::resize(m, out, cv::Size(size, size), 0, 0, image.width > size ? cv::INTER_AREA : cv::INTER_LINEAR);
  return out;
}

// The fused textures of frame `frame_dir` (TAKE/derived/textures/frame-NNNNNN: texture fusion's albedo, specular
// intensity and tangent-space normals) at `size`; valid where at least half of the texel was covered by a view.
absl::StatusOr<FrameTextures> FusedFrameTextures(int size, const std::string& frame_dir) {
  STAGE_ASSIGN_OR_RETURN(const FusedTextures fused, ReadFusedTextures(frame_dir));
  Image covered(fused.size, fused.size, 1);
  for (size_t i = 0; i < fused.state.size(); ++i) covered.pixels[i] = fused.state[i] == TexelState::kCovered;
  const cv::Mat albedo = ResizedMap(fused.albedo, size), specular = ResizedMap(fused.specular, size),
                normal = ResizedMap(fused.normal_tangent, size), valid = ResizedMap(covered, size);
  FrameTextures t;
  t.maps.assign(static_cast<size_t>(size) * size * kTextureChannels, 0.f);
  t.valid.assign(static_cast<size_t>(size) * size, 0);
  for (int row = 0; row < size; ++row) {
    for (int col = 0; col < size; ++col) {
      const size_t i = static_cast<size_t>(row) * size + col;
      const cv::Vec3f n = normal.at<cv::Vec3f>(row, col);
      if (valid.at<float>(row, col) < 0.5f || cv::norm(n) == 0) continue;
      float* m = &t.maps[kTextureChannels * i];
      const cv::Vec3f a = albedo.at<cv::Vec3f>(row, col);
      const cv::Vec3f unit = n / cv::norm(n);
      m[0] = a[0], m[1] = a[1], m[2] = a[2], m[3] = specular.at<float>(row, col);
      m[4] = unit[0], m[5] = unit[1], m[6] = unit[2];
      t.valid[i] = 1;
    }
  }
  return t;
}

// Where a dataset's full-resolution neutral textures are: beside its file, named for it (the file is the same bytes
// wherever it was written, so that the three ways of building it agree).
std::string NeutralTexturesDir(const std::string& dataset_path) {
  const fs::path p(dataset_path);
  return (p.parent_path() / (p.stem().string() + "-neutral")).string();
}

// The texels the template's layout covers at `size` (with the map's dilation past its edges): the truth is drawn
// there.
absl::StatusOr<std::vector<uint8_t>> TemplateLayout(const FaceTemplate& face, int size) {
  STAGE_ASSIGN_OR_RETURN(const GeometryMap map,
                         MakeGeometryMap(face.mesh, Eigen::Isometry3f::Identity(), {.size = size}));
  std::vector<uint8_t> layout(map.state.size());
  for (size_t t = 0; t < map.state.size(); ++t) layout[t] = map.state[t] != TexelState::kEmpty;
  return layout;
}

// The textures of the source's frame `frame_dir` at `size` texels across: the truth's (drawn where `layout`,
// TemplateLayout's at that size, covers) or texture fusion's.
absl::StatusOr<FrameTextures> SourceTextures(const FaceTemplate& face, bool truth, const std::vector<uint8_t>& layout,
                                             int size, const std::string& frame_dir) {
  return truth ? TruthTextures(face, layout, size, frame_dir) : FusedFrameTextures(size, frame_dir);
}

// The neutral frame's (`frame_dir`'s) textures at full resolution beside the dataset (DatasetOptions::
// neutral_texture_size); 0 takes the size of the source's albedo.
absl::Status WriteNeutralTextures(const DatasetOptions& options, const FaceTemplate& face, bool truth,
                                  const std::string& frame_dir, DatasetSummary* summary) {
  int size = options.neutral_texture_size;
  if (size == 0) {
    const std::string albedo = frame_dir + (truth ? "/uv_albedo.exr" : "/albedo.exr");
    STAGE_ASSIGN_OR_RETURN(const Image source, ReadImageFile(albedo));
    size = source.width;
  }
  std::vector<uint8_t> layout;  // the truth's only
  if (truth) {
    STAGE_ASSIGN_OR_RETURN(layout, TemplateLayout(face, size));
  }
  STAGE_ASSIGN_OR_RETURN(const FrameTextures t, SourceTextures(face, truth, layout, size, frame_dir));
  const std::string dir = NeutralTexturesDir(summary->path);
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  Image albedo(size, size, 4), specular(size, size, 1), normal(size, size, 3);
  for (size_t i = 0; i < t.valid.size(); ++i) {
    const float* m = &t.maps[kTextureChannels * i];
    std::copy(m, m + 3, &albedo.pixels[4 * i]);
    albedo.pixels[4 * i + 3] = t.valid[i];
    specular.pixels[i] = m[3];
    std::copy(m + 4, m + 7, &normal.pixels[3 * i]);
  }
  STAGE_RETURN_IF_ERROR(WriteExr(dir + "/albedo.exr", albedo));
  STAGE_RETURN_IF_ERROR(WriteExr(dir + "/specular.exr", specular));
  STAGE_RETURN_IF_ERROR(WriteExr(dir + "/normal_tangent.exr", normal));
  summary->neutral_textures_dir = dir;
  summary->neutral_texture_size = size;
  return absl::OkStatus();
}

// The sequence each frame's truth names ("" where there is no truth or it names none).
std::vector<std::string> FrameSequences(const std::string& take_dir, const std::vector<int64_t>& frames) {
  std::vector<std::string> out;
  for (int64_t f : frames) {
    std::ifstream in(FrameDir(take_dir + "/ground_truth", f) + "/pose.json");
    const nlohmann::json j = in ? nlohmann::json::parse(in, nullptr, false) : nlohmann::json();
    out.push_back(
        j.is_object() && j.contains("sequence") && j["sequence"].is_string() ? j["sequence"].get<std::string>() : "");
  }
  return out;
}

// The sequence held out: the one named, or the last the frames hold whole (the first and the last named may be cut
// by the take's ends). -1: none.
absl::StatusOr<int32_t> HeldOutSequence(const DatasetOptions& options, const std::vector<std::string>& names) {
  if (options.held_out_sequence == "none") return -1;
  if (!options.held_out_sequence.empty()) {
    for (size_t i = 0; i < names.size(); ++i) {
      if (names[i] == options.held_out_sequence) return static_cast<int32_t>(i);
    }
    std::string known;
    for (const std::string& n : names) absl::StrAppend(&known, known.empty() ? "" : ", ", n);
    return absl::NotFoundError(absl::StrCat(options.take_dir, ": no frame of sequence \"", options.held_out_sequence,
                                            "\" (", known.empty() ? "the take names no sequences" : known, ")"));
  }
  if (names.size() < 3) return -1;
  // Sequences are numbered in the order they are first met: the last whole one is the one before the last.
  return static_cast<int32_t>(names.size()) - 2;
}

// How far the frames' maps spread about their per-texel mean (RMS of the 3D distance over valid texels), accumulated
// a frame at a time (Welford's update), so that no frame has to stay in memory for it.
class RunningSpread {
 public:
  void Add(const std::vector<float>& points, const std::vector<uint8_t>& valid) {
    if (count_.empty()) {
      count_.assign(valid.size(), 0);
      mean_.assign(points.size(), 0);
      m2_.assign(points.size(), 0);
    }
    for (size_t t = 0; t < valid.size(); ++t) {
      if (!valid[t]) continue;
      const double n = ++count_[t];
      for (size_t c = 3 * t; c < 3 * t + 3; ++c) {
        const double delta = points[c] - mean_[c];
        mean_[c] += delta / n;
        m2_[c] += delta * (points[c] - mean_[c]);
      }
    }
  }
  double Rms() const {
    double se = 0, n = 0;
    for (size_t t = 0; t < count_.size(); ++t) {
      n += count_[t];
      se += m2_[3 * t] + m2_[3 * t + 1] + m2_[3 * t + 2];
    }
    return n > 0 ? std::sqrt(se / n) : 0;
  }

 private:
  std::vector<double> count_, mean_, m2_;
};

// Each camera's crops of the dataset's frames: a fixed square about where the face is when the head is at rest.
struct Crops {
  std::vector<std::string> cameras;
  std::vector<nlohmann::json> boxes;               // per camera: centre and side, pixels of its frames
  std::map<int64_t, std::vector<uint8_t>> images;  // frame -> cameras x size^2
  std::map<int64_t, std::vector<uint8_t>> valid;   // frame -> cameras
};

// The grey frame's (width x height floats) square of `side` pixels about `centre` (sub-pixel).
cv::Mat Patch(const float* grey, int width, int height, const Eigen::Vector2d& centre, double side) {
  const cv::Mat frame(height, width, CV_32F, const_cast<float*>(grey));
  const int s = std::max(2, static_cast<int>(std::lround(side)));
  cv::Mat patch;
  cv::getRectSubPix(frame, cv::Size(s, s), cv::Point2f(static_cast<float>(centre.x()), static_cast<float>(centre.y())),
                    patch);
  return patch;
}

// A patch's white: its 99.5th percentile (at least 1 DN).
double White(const cv::Mat& patch) {
  std::vector<float> values(patch.begin<float>(), patch.end<float>());
  const size_t k = static_cast<size_t>(0.995 * static_cast<double>(values.size() - 1));
  std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(k), values.end());
  return std::max(1.0, static_cast<double>(values[k]));
}

// A patch averaged down to size x size and mapped to 8 bits over `white` (through 1 / gamma).
std::vector<uint8_t> Crop(const cv::Mat& patch, int size, double white, double gamma = 2.2) {
  cv::Mat small;
  cv::resize(patch, small, cv::Size(size, size), 0, 0, patch.cols > size ? cv::INTER_AREA : cv::INTER_LINEAR);
  std::vector<uint8_t> out(static_cast<size_t>(size) * size);
  for (int i = 0; i < size * size; ++i) {
    const double v = std::clamp(small.at<float>(i / size, i % size) / white, 0.0, 1.0);
    out[static_cast<size_t>(i)] = static_cast<uint8_t>(std::lround(255 * std::pow(v, 1 / gamma)));
  }
  return out;
}

// The take's cameras (`options.cameras`, or every machine-vision camera with a frame file; none: no crops), each
// frame of `frames` cropped.
absl::StatusOr<Crops> CropImages(const DatasetOptions& options, const FaceTemplate& face,
                                 const std::vector<int64_t>& frames) {
  Crops crops;
  if (!fs::exists(options.take_dir + "/take.json")) {
    if (!options.cameras.empty()) {
      return absl::NotFoundError(
          absl::StrCat(options.take_dir, "/take.json: cannot open (the take's rig and cameras)"));
    }
    return crops;
  }
  STAGE_ASSIGN_OR_RETURN(const LoadedRig rig, LoadTakeRig(options.take_dir));
  std::vector<std::string> ids = options.cameras;
  if (ids.empty()) {
    for (const v1::CameraConfig& c : rig.rig.cameras()) {
      if (c.role() == v1::CAMERA_ROLE_MACHINE_VISION && fs::exists(options.take_dir + "/cameras/" + c.id() + ".h5")) {
        ids.push_back(c.id());
      }
    }
  }
  if (ids.empty()) return crops;
  STAGE_ASSIGN_OR_RETURN(const LightModel light, LightModel::FromRig(rig));
  STAGE_ASSIGN_OR_RETURN(const std::optional<CameraCalibration> calibration,
                         LoadJobCalibration(options.take_dir, options.calibration));
  STAGE_ASSIGN_OR_RETURN(const std::vector<TakeCamera> cameras,
                         OpenTakeCameras(options.take_dir, rig, ids, calibration ? &*calibration : nullptr));
  // The face's centre: the template's vertices' mean, the head at rest (its frame the stage's).
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3f& p : face.mesh.positions) centre += p.cast<double>();
  centre /= static_cast<double>(face.mesh.positions.size());
  const size_t n = cameras.size(), texels = static_cast<size_t>(options.image_size) * options.image_size;
  for (int64_t f : frames) {
    crops.images[f].assign(n * texels, 0);
    crops.valid[f].assign(n, 0);
  }
  for (size_t c = 0; c < n; ++c) {
    const TakeCamera& camera = cameras[c];
    Eigen::Vector2d pixel;
    if (!camera.model.Project(centre, &pixel)) {
      return absl::InvalidArgumentError(absl::StrCat(camera.id, ": the face is behind the camera"));
    }
    const double depth = camera.model.rotation().row(2).dot(centre - camera.model.position());
    const double side = options.crop_mm * camera.model.fx() / depth;
    crops.cameras.push_back(camera.id);
    double white = 0;  // the camera's first crop's 99.5th percentile: one scale for all its frames
    STAGE_RETURN_IF_ERROR(ForEachFullLitFrame(
        camera.path, frames.front(), frames.back() + 1, light, camera.black_level_dn,
        [&](int64_t frame, const Image& grey) -> absl::Status {
          if (options.cancelled && options.cancelled()) {
            return absl::CancelledError(absl::StrCat("dataset: stopped cropping ", camera.id, " (nothing written)"));
          }
          auto slot = crops.images.find(frame);
          if (slot == crops.images.end()) return absl::OkStatus();
          const cv::Mat patch = Patch(grey.pixels.data(), grey.width, grey.height, pixel, side);
          if (white == 0) white = White(patch);
          const std::vector<uint8_t> image = Crop(patch, options.image_size, white);
          std::copy(image.begin(), image.end(), slot->second.begin() + static_cast<std::ptrdiff_t>(c * texels));
          crops.valid[frame][c] = 1;
          return absl::OkStatus();
        }));
    // Where and how bright: what cropping a new frame of the camera the same way needs (CropBox).
    crops.boxes.push_back(
        {{"camera", camera.id}, {"centre_px", {pixel.x(), pixel.y()}}, {"side_px", side}, {"white_dn", white}});
  }
  return crops;
}

// Sequence ids of the frames' names (-1 for none), numbered in the order the frames first meet them, into
// `sequences`.
std::vector<int32_t> NumberSequences(const std::vector<std::string>& names, std::vector<std::string>* sequences) {
  std::vector<int32_t> ids;
  for (const std::string& name : names) {
    if (name.empty()) {
      ids.push_back(-1);
      continue;
    }
    auto it = std::find(sequences->begin(), sequences->end(), name);
    if (it == sequences->end()) it = sequences->insert(sequences->end(), name);
    ids.push_back(static_cast<int32_t>(it - sequences->begin()));
  }
  return ids;
}

// The dataset's arrays (asset_dataset.h), the images' only with `views` cameras.
absl::Status AddArrays(storage::ArrayFileWriter& writer, int size, int64_t views, int image_size, int texture_size) {
  STAGE_RETURN_IF_ERROR(writer.AddArray("frame", ArrayType::kInt64, {}));
  if (texture_size > 0) {
    STAGE_RETURN_IF_ERROR(
        writer.AddArray("textures", ArrayType::kFloat32, {texture_size, texture_size, kTextureChannels}));
    STAGE_RETURN_IF_ERROR(writer.AddArray("texture_valid", ArrayType::kUint8, {texture_size, texture_size}, 4));
  }
  STAGE_RETURN_IF_ERROR(writer.AddArray("split", ArrayType::kUint8, {}));
  STAGE_RETURN_IF_ERROR(writer.AddArray("sequence", ArrayType::kInt32, {}));
  STAGE_RETURN_IF_ERROR(writer.AddArray("geometry", ArrayType::kFloat32, {size, size, 3}));
  STAGE_RETURN_IF_ERROR(writer.AddArray("valid", ArrayType::kUint8, {size, size}, /*deflate=*/4));
  STAGE_RETURN_IF_ERROR(writer.AddArray("stage_from_head", ArrayType::kFloat32, {4, 4}));
  if (views == 0) return absl::OkStatus();
  STAGE_RETURN_IF_ERROR(writer.AddArray("images", ArrayType::kUint8, {views, image_size, image_size}, /*deflate=*/1));
  return writer.AddArray("image_valid", ArrayType::kUint8, {views});
}

// The dataset's description attribute.
nlohmann::json Description(const DatasetOptions& options, const FaceTemplate& face, const DatasetSummary& summary,
                           const Crops& crops) {
  nlohmann::json d;
  d["source"] = AssetSourceName(options.source);
  d["take"] = fs::absolute(options.take_dir).lexically_normal().string();
  d["geometry_size"] = summary.geometry_size;
  d["template"] = face.source;
  d["sequences"] = summary.sequences;
  d["held_out_sequence"] = summary.sequence;
  d["held_out_fraction"] = options.held_out_fraction;
  d["held_out_blocks"] = options.held_out_blocks;
  d["cameras"] = crops.cameras;
  d["image_size"] = summary.image_size;
  d["texture_size"] = summary.texture_size;
  if (summary.texture_size > 0) {
    d["texture_channels"] = {"albedo_r", "albedo_g", "albedo_b", "specular", "normal_x", "normal_y", "normal_z"};
  }
  d["crop_mm"] = options.crop_mm;
  d["crops"] = crops.boxes;
  d["splits"] = {{"train", summary.train},
                 {"held_out_block", summary.held_out_block},
                 {"held_out_sequence", summary.held_out_sequence}};
  return d;
}

}  // namespace

const char* AssetSourceName(AssetSource source) { return source == AssetSource::kTruth ? "truth" : "reconstruction"; }

absl::StatusOr<AssetSource> ParseAssetSource(const std::string& name) {
  if (name == "truth") return AssetSource::kTruth;
  if (name == "reconstruction") return AssetSource::kReconstruction;
  return absl::InvalidArgumentError(absl::StrCat("source \"", name, "\" is not truth or reconstruction"));
}

const char* SampleSplitName(SampleSplit split) {
  switch (split) {
    case SampleSplit::kTrain:
      return "train";
    case SampleSplit::kHeldOutBlock:
      return "held_out_block";
    case SampleSplit::kHeldOutSequence:
      return "held_out_sequence";
  }
  return "?";
}

absl::Status DatasetOptions::Validate() const {
  if (take_dir.empty()) return absl::InvalidArgumentError("dataset: no take directory");
  if (geometry_size < 16 || geometry_size > 1024) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: geometry size ", geometry_size, " is not in 16..1024"));
  }
  if (!(held_out_fraction >= 0 && held_out_fraction <= 0.5)) {
    return absl::InvalidArgumentError(
        absl::StrCat("dataset: held-out fraction ", held_out_fraction, " is not in [0, 0.5]"));
  }
  if (texture_size != 0 && (texture_size < 16 || texture_size > 1024)) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: texture size ", texture_size, " is not 0 or 16..1024"));
  }
  if (neutral_texture_size != 0 && neutral_texture_size != -1 &&
      (neutral_texture_size < 16 || neutral_texture_size > 8192)) {
    return absl::InvalidArgumentError(
        absl::StrCat("dataset: neutral texture size ", neutral_texture_size, " is not -1, 0 or 16..8192"));
  }
  if (neutral_texture_size > 0 && texture_size == 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("dataset: neutral texture size ", neutral_texture_size, " with no textures (texture size 0)"));
  }
  if (image_size < 16 || image_size > 512) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: image size ", image_size, " is not in 16..512"));
  }
  if (!(crop_mm >= 50 && crop_mm <= 1000)) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: crop of ", crop_mm, " mm is not in 50..1000"));
  }
  if (held_out_blocks < 1 || held_out_blocks > 64) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: held-out blocks ", held_out_blocks, " is not in 1..64"));
  }
  if (first_frame < 0 || (last_frame >= 0 && last_frame <= first_frame)) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: frames [", first_frame, ", ", last_frame, ") are empty"));
  }
  if (frame_step < 1 || frame_step > 1000) {
    return absl::InvalidArgumentError(absl::StrCat("dataset: frame step ", frame_step, " is not in 1..1000"));
  }
  return absl::OkStatus();
}

std::vector<SampleSplit> SplitFrames(const std::vector<int32_t>& sequence, int32_t held_out, double fraction,
                                     int blocks) {
  std::vector<SampleSplit> split(sequence.size(), SampleSplit::kTrain);
  std::vector<size_t> rest;
  for (size_t i = 0; i < sequence.size(); ++i) {
    if (held_out >= 0 && sequence[i] == held_out) {
      split[i] = SampleSplit::kHeldOutSequence;
    } else {
      rest.push_back(i);
    }
  }
  const double n = static_cast<double>(rest.size());
  const int64_t block = static_cast<int64_t>(std::llround(n * fraction / blocks));
  if (block == 0) return split;
  for (int b = 0; b < blocks; ++b) {
    // Block b centred at (b + 1/2) / blocks of the way through the remaining frames.
    const int64_t start = std::clamp<int64_t>(static_cast<int64_t>(std::llround((b + 0.5) / blocks * n)) - block / 2, 0,
                                              static_cast<int64_t>(rest.size()) - block);
    for (int64_t i = start; i < start + block; ++i) split[rest[static_cast<size_t>(i)]] = SampleSplit::kHeldOutBlock;
  }
  return split;
}

absl::StatusOr<DatasetSummary> BuildAssetDataset(const DatasetOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (!fs::is_directory(options.take_dir)) {
    return absl::NotFoundError(absl::StrCat(options.take_dir, ": no such take directory"));
  }
  const bool truth = options.source == AssetSource::kTruth;
  const std::string root = options.take_dir + (truth ? "/ground_truth" : "/derived/fit");
  const std::string file = truth ? "uv_position.exr" : "geometry_map.exr";
  std::vector<int64_t> frames = ListFrames(root, file, options.first_frame, options.last_frame);
  for (size_t i = 0; i * options.frame_step < frames.size(); ++i) frames[i] = frames[i * options.frame_step];
  frames.resize((frames.size() + options.frame_step - 1) / options.frame_step);
  if (frames.empty()) {
    return absl::NotFoundError(absl::StrCat(
        root, ": no frame-NNNNNN/", file, " in frames [", options.first_frame, ", ",
        options.last_frame < 0 ? "end" : std::to_string(options.last_frame), ")",
        truth ? " (the take has no ground truth: a real take, or not recorded)" : " (run `stage-process fit` first)"));
  }
  STAGE_ASSIGN_OR_RETURN(const FaceTemplate face, ShippedFaceTemplate());
  const int size = options.geometry_size;
  STAGE_ASSIGN_OR_RETURN(const std::vector<uint8_t> layout, TemplateLayout(face, size));

  std::vector<std::string> sequences;
  const std::vector<int32_t> ids = NumberSequences(FrameSequences(options.take_dir, frames), &sequences);
  STAGE_ASSIGN_OR_RETURN(const int32_t held_out, HeldOutSequence(options, sequences));
  const std::vector<SampleSplit> split = SplitFrames(ids, held_out, options.held_out_fraction, options.held_out_blocks);

  DatasetSummary summary;
  summary.path = options.output.empty() ? options.take_dir + "/derived/asset/dataset.h5" : options.output;
  summary.source = options.source;
  summary.geometry_size = size;
  summary.frames = static_cast<int64_t>(frames.size());
  summary.sequences = sequences;
  if (held_out >= 0) summary.sequence = sequences[static_cast<size_t>(held_out)];
  for (SampleSplit s : split) {
    (s == SampleSplit::kTrain          ? summary.train
     : s == SampleSplit::kHeldOutBlock ? summary.held_out_block
                                       : summary.held_out_sequence)++;
  }
  {
    std::error_code ec;
    fs::create_directories(fs::path(summary.path).parent_path(), ec);
    if (ec) return absl::UnavailableError(absl::StrCat(summary.path, ": ", ec.message()));
  }
  // The textures, where the source has them.
  const std::string texture_root = truth ? root : options.take_dir + "/derived/textures";
  const std::string texture_file = truth ? "uv_albedo.exr" : "albedo.exr";
  std::vector<uint8_t> texture_layout;
  if (options.texture_size == 0) {
    summary.textures_note = "none asked for (texture size 0)";
  } else if (!fs::exists(FrameDir(texture_root, frames.front()) + "/" + texture_file)) {
    summary.textures_note =
        absl::StrCat("none: ", FrameDir(texture_root, frames.front()), " has no ", texture_file,
                     truth ? " (render the truth with --uv-textures)" : " (run `stage-process textures` first)");
  } else {
    summary.texture_size = options.texture_size;
    STAGE_ASSIGN_OR_RETURN(texture_layout, TemplateLayout(face, options.texture_size));
  }
  STAGE_ASSIGN_OR_RETURN(auto writer, storage::ArrayFileWriter::Create(summary.path));
  STAGE_ASSIGN_OR_RETURN(const Crops crops, CropImages(options, face, frames));
  const int64_t views = static_cast<int64_t>(crops.cameras.size());
  STAGE_RETURN_IF_ERROR(AddArrays(*writer, size, views, options.image_size, summary.texture_size));
  summary.cameras = crops.cameras;
  summary.image_size = views > 0 ? options.image_size : 0;
  RunningSpread spread;
  double valid_texels = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (options.cancelled && options.cancelled()) {
      return absl::CancelledError(absl::StrCat("dataset: stopped at frame ", frames[i], " (nothing written)"));
    }
    const std::string frame_dir = FrameDir(root, frames[i]);
    absl::StatusOr<FrameGeometry> g =
        truth ? TruthGeometry(face, layout, size, frame_dir) : FitGeometry(size, frame_dir);
    if (!g.ok()) return g.status();
    const uint8_t s = static_cast<uint8_t>(split[i]);
    const Eigen::Matrix<float, 4, 4, Eigen::RowMajor> pose = g->stage_from_head;
    STAGE_RETURN_IF_ERROR(writer->Append("frame", &frames[i]));
    STAGE_RETURN_IF_ERROR(writer->Append("split", &s));
    STAGE_RETURN_IF_ERROR(writer->Append("sequence", &ids[i]));
    STAGE_RETURN_IF_ERROR(writer->Append("geometry", g->points.data()));
    STAGE_RETURN_IF_ERROR(writer->Append("valid", g->valid.data()));
    STAGE_RETURN_IF_ERROR(writer->Append("stage_from_head", pose.data()));
    if (views > 0) {
      STAGE_RETURN_IF_ERROR(writer->Append("images", crops.images.at(frames[i]).data()));
      STAGE_RETURN_IF_ERROR(writer->Append("image_valid", crops.valid.at(frames[i]).data()));
    }
    if (summary.texture_size > 0) {
      const std::string dir = FrameDir(texture_root, frames[i]);
      absl::StatusOr<FrameTextures> t = SourceTextures(face, truth, texture_layout, summary.texture_size, dir);
      if (!t.ok()) return t.status();
      STAGE_RETURN_IF_ERROR(writer->Append("textures", t->maps.data()));
      STAGE_RETURN_IF_ERROR(writer->Append("texture_valid", t->valid.data()));
    }
    valid_texels += static_cast<double>(std::count(g->valid.begin(), g->valid.end(), 1));
    spread.Add(g->points, g->valid);
    if (options.progress) options.progress(static_cast<int64_t>(i) + 1, static_cast<int64_t>(frames.size()));
  }
  if (summary.texture_size > 0 && options.neutral_texture_size >= 0) {
    STAGE_RETURN_IF_ERROR(WriteNeutralTextures(options, face, truth, FrameDir(texture_root, frames.front()), &summary));
  }
  summary.valid_texels = valid_texels / static_cast<double>(frames.size());
  summary.rms_from_mean_mm = spread.Rms();
  STAGE_RETURN_IF_ERROR(writer->SetAttribute("format", kFormat));
  STAGE_RETURN_IF_ERROR(writer->SetAttribute("description", Description(options, face, summary, crops).dump()));
  if (summary.neutral_texture_size > 0) {
    const nlohmann::json neutral = {{"size", summary.neutral_texture_size}};
    STAGE_RETURN_IF_ERROR(writer->SetAttribute("neutral_textures", neutral.dump()));
  }
  STAGE_RETURN_IF_ERROR(writer->Close());
  return summary;
}

namespace {

// The description attribute read into `d` (sizes, sequences, cameras, crops).
absl::Status ReadDescription(const storage::ArrayFileReader& reader, const std::string& path, AssetDataset* d) {
  auto format = reader.Attribute("format");
  if (!format.ok() || *format != kFormat) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a FaStage asset dataset (format \"",
                                                   format.ok() ? *format : "", "\", expected ", kFormat, ")"));
  }
  d->path = path;
  STAGE_ASSIGN_OR_RETURN(d->description, reader.Attribute("description"));
  const nlohmann::json j = nlohmann::json::parse(d->description, nullptr, false);
  if (!j.is_object() || !j.contains("sequences") || !j.contains("geometry_size")) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": the description is not a dataset's"));
  }
  try {
    d->sequences = j["sequences"].get<std::vector<std::string>>();
    d->geometry_size = j["geometry_size"].get<int>();
    d->cameras = j.value("cameras", std::vector<std::string>());
    d->image_size = j.value("image_size", 0);
    d->texture_size = j.value("texture_size", 0);
    // Apart from the description, which is the dataset's identity for training (the nets never see these).
    if (auto neutral = reader.Attribute("neutral_textures"); neutral.ok()) {
      d->neutral_textures_dir = NeutralTexturesDir(path);
      d->neutral_texture_size = nlohmann::json::parse(*neutral).at("size").get<int>();
    }
    for (const nlohmann::json& box : j.value("crops", nlohmann::json::array())) {
      if (!box.contains("white_dn")) continue;  // written before the white was kept
      d->crops.push_back({box.at("camera").get<std::string>(), box.at("centre_px").at(0).get<double>(),
                          box.at("centre_px").at(1).get<double>(), box.at("side_px").get<double>(),
                          box.at("white_dn").get<double>()});
    }
  } catch (const nlohmann::json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": the description does not read: ", e.what()));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<AssetDataset> ReadAssetDatasetDescription(const std::string& path) {
  STAGE_ASSIGN_OR_RETURN(auto reader, storage::ArrayFileReader::Open(path));
  AssetDataset d;
  STAGE_RETURN_IF_ERROR(ReadDescription(*reader, path, &d));
  return d;
}

absl::Status ReadDatasetFrameTextures(const AssetDataset& d, int64_t i, std::vector<float>* maps,
                                      std::vector<uint8_t>* valid) {
  if (d.texture_size == 0)
    return absl::FailedPreconditionError(absl::StrCat(d.path, ": the dataset holds no textures"));
  STAGE_ASSIGN_OR_RETURN(auto reader, storage::ArrayFileReader::Open(d.path));
  const size_t texels = static_cast<size_t>(d.texture_size) * d.texture_size;
  maps->resize(texels * kTextureChannels);
  valid->resize(texels);
  STAGE_RETURN_IF_ERROR(reader->ReadRows("textures", ArrayType::kFloat32, i, 1, maps->data()));
  return reader->ReadRows("texture_valid", ArrayType::kUint8, i, 1, valid->data());
}

absl::StatusOr<AssetDataset> ReadAssetDataset(const std::string& path) {
  STAGE_ASSIGN_OR_RETURN(auto reader, storage::ArrayFileReader::Open(path));
  AssetDataset d;
  STAGE_RETURN_IF_ERROR(ReadDescription(*reader, path, &d));
  STAGE_ASSIGN_OR_RETURN(d.frame, reader->ReadAll<int64_t>("frame"));
  STAGE_ASSIGN_OR_RETURN(const std::vector<uint8_t> split, reader->ReadAll<uint8_t>("split"));
  STAGE_ASSIGN_OR_RETURN(d.sequence, reader->ReadAll<int32_t>("sequence"));
  STAGE_ASSIGN_OR_RETURN(d.geometry, reader->ReadAll<float>("geometry"));
  STAGE_ASSIGN_OR_RETURN(d.valid, reader->ReadAll<uint8_t>("valid"));
  STAGE_ASSIGN_OR_RETURN(d.stage_from_head, reader->ReadAll<float>("stage_from_head"));
  const size_t n = d.frame.size(), texels = static_cast<size_t>(d.geometry_size) * d.geometry_size;
  if (!d.cameras.empty()) {
    STAGE_ASSIGN_OR_RETURN(d.images, reader->ReadAll<uint8_t>("images"));
    STAGE_ASSIGN_OR_RETURN(d.image_valid, reader->ReadAll<uint8_t>("image_valid"));
    const size_t views = d.cameras.size(), pixels = static_cast<size_t>(d.image_size) * d.image_size;
    if (d.images.size() != n * views * pixels || d.image_valid.size() != n * views) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": images of disagreeing lengths"));
    }
  }
  if (d.texture_size > 0) {
    STAGE_ASSIGN_OR_RETURN(d.textures, reader->ReadAll<float>("textures"));
    STAGE_ASSIGN_OR_RETURN(d.texture_valid, reader->ReadAll<uint8_t>("texture_valid"));
    const size_t texture_texels = static_cast<size_t>(d.texture_size) * d.texture_size;
    if (d.textures.size() != n * texture_texels * kTextureChannels || d.texture_valid.size() != n * texture_texels) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": textures of disagreeing lengths"));
    }
  }
  if (split.size() != n || d.sequence.size() != n || d.geometry.size() != n * texels * 3 ||
      d.valid.size() != n * texels || d.stage_from_head.size() != n * 16) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": arrays of disagreeing lengths"));
  }
  for (uint8_t s : split) {
    if (s > 2) return absl::InvalidArgumentError(absl::StrCat(path, ": split value ", s, " is not 0, 1 or 2"));
    d.split.push_back(static_cast<SampleSplit>(s));
  }
  return d;
}

absl::StatusOr<CropBox> DatasetCropBox(const AssetDataset& d, const std::string& camera) {
  for (const CropBox& box : d.crops) {
    if (box.camera == camera) return box;
  }
  std::vector<std::string> ids;
  for (const CropBox& box : d.crops) ids.push_back(box.camera);
  return absl::NotFoundError(absl::StrCat(d.path, ": no crop of camera \"", camera, "\" (it cropped: ",
                                          ids.empty() ? "none kept: rebuild it" : absl::StrJoin(ids, ", "), ")"));
}

std::vector<uint8_t> CropFrame(const float* grey, int width, int height, const CropBox& box, int size, double white,
                               double gamma) {
  return Crop(Patch(grey, width, height, {box.centre_x, box.centre_y}, box.side), size, white, gamma);
}

double CropWhite(const float* grey, int width, int height, const CropBox& box) {
  return White(Patch(grey, width, height, {box.centre_x, box.centre_y}, box.side));
}

absl::Status ForEachTakeCrop(const std::string& take_dir, const CropBox& box, int size, int64_t first, int64_t last,
                             const std::function<absl::Status(int64_t, const std::vector<uint8_t>&)>& fn) {
  if (!(box.white > 0)) {
    return absl::FailedPreconditionError(
        absl::StrCat("camera ", box.camera, ": its crops have no white (the dataset saw no frame of it)"));
  }
  STAGE_ASSIGN_OR_RETURN(const LoadedRig rig, LoadTakeRig(take_dir));
  STAGE_ASSIGN_OR_RETURN(const LightModel light, LightModel::FromRig(rig));
  STAGE_ASSIGN_OR_RETURN(const std::vector<TakeCamera> cameras, OpenTakeCameras(take_dir, rig, {box.camera}, nullptr));
  const TakeCamera& camera = cameras.front();
  const int64_t cycle = static_cast<int64_t>(light.patterns.size());
  const int64_t end = last < 0 ? camera.last_slot / std::max<int64_t>(1, cycle) + 1 : last;
  return ForEachFullLitFrame(
      camera.path, first, end, light, camera.black_level_dn, [&](int64_t frame, const Image& grey) -> absl::Status {
        return fn(frame, CropFrame(grey.pixels.data(), grey.width, grey.height, box, size, box.white, /*gamma=*/2.2));
      });
}

}  // namespace stage::processing
