// Ground truth files.
#include "stage/sim/ground_truth.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/status.h"
#include "stage/common/uv_raster.h"

namespace stage::sim {
namespace {

namespace fs = std::filesystem;

absl::Status Write(const std::string& path, const cv::Mat& image) {
  bool ok = false;
  try {
    ok = cv::imwrite(path, image);
  } catch (const cv::Exception& e) {
    return absl::UnavailableError(absl::StrCat(path, ": ", e.what()));
  }
  if (!ok) return absl::UnavailableError(absl::StrCat(path, ": cannot write the image"));
  return absl::OkStatus();
}

// OpenCV writes channels as B, G, R: put the values' x, y, z (or R, G, B) in that order.
cv::Vec3f Bgr(const Eigen::Vector3f& v) { return {v.z(), v.y(), v.x()}; }

// An RGBA map (row 0 at v = 1) as an OpenEXR file.
absl::Status WriteRgba(const std::string& path, const std::vector<float>& rgba, int size) {
  cv::Mat image(size, size, CV_32FC4, const_cast<float*>(rgba.data()));
  cv::Mat bgra;
  cv::cvtColor(image, bgra, cv::COLOR_RGBA2BGRA);
  return Write(path, bgra);
}

}  // namespace

UvMaterialMaps UvMaterials(const RiggedModel& model, const HeadPose& pose, int size) {
  HeadPose still;  // the expression in the head's frame: no turn, no move
  still.expression = pose.expression;
  const TriangleMesh mesh = model.PosedMesh(still);
  const std::vector<UvTexel> texels = RasterizeUv(mesh, size, /*part=*/0);
  const std::vector<Eigen::Vector3f> normals = mesh.VertexNormals();
  const size_t n = static_cast<size_t>(size) * size;
  UvMaterialMaps maps;
  maps.albedo.assign(4 * n, 0.f);
  maps.material.assign(4 * n, 0.f);
  maps.normal.assign(4 * n, 0.f);
  for (size_t i = 0; i < n; ++i) {
    const UvTexel& texel = texels[i];
    if (!texel.covered()) continue;
    const auto& tr = mesh.triangles[static_cast<size_t>(texel.triangle)];
    const float b0 = 1 - texel.b1 - texel.b2;
    const Eigen::Vector2f uv = b0 * mesh.uvs[tr[0]] + texel.b1 * mesh.uvs[tr[1]] + texel.b2 * mesh.uvs[tr[2]];
    const SurfaceSample s = model.Surface(uv, 0, pose.expression);
    Eigen::Vector3f normal = (b0 * normals[tr[0]] + texel.b1 * normals[tr[1]] + texel.b2 * normals[tr[2]]).normalized();
    Eigen::Vector3f pu, pv;
    const Eigen::Vector3f& p0 = mesh.positions[tr[0]];
    if (TriangleTangents(mesh.positions[tr[1]] - p0, mesh.positions[tr[2]] - p0, mesh.uvs[tr[1]] - mesh.uvs[tr[0]],
                         mesh.uvs[tr[2]] - mesh.uvs[tr[0]], &pu, &pv)) {
      normal = DetailedNormal(normal, pu, pv, s);
    }
    std::copy(s.material.albedo.data(), s.material.albedo.data() + 3, &maps.albedo[4 * i]);
    maps.material[4 * i] = s.material.specular;
    maps.material[4 * i + 1] = s.material.roughness;
    std::copy(normal.data(), normal.data() + 3, &maps.normal[4 * i]);
    maps.albedo[4 * i + 3] = maps.material[4 * i + 3] = maps.normal[4 * i + 3] = 1;
  }
  return maps;
}

std::vector<float> UvPositionMap(const TriangleMesh& mesh, int size) {
  const std::vector<UvTexel> texels = RasterizeUv(mesh, size, /*part=*/0);
  std::vector<float> map(static_cast<size_t>(size) * size * 4, 0.0f);
  const std::vector<Eigen::Vector3f> points =
      InterpolateAtTexels(mesh, texels, mesh.positions, Eigen::Vector3f::Zero());
  for (size_t i = 0; i < texels.size(); ++i) {
    if (!texels[i].covered()) continue;
    std::copy(points[i].data(), points[i].data() + 3, &map[4 * i]);
    map[4 * i + 3] = 1;
  }
  return map;
}

absl::Status GroundTruthOptions::Validate() const {
  if (last_frame <= first_frame) {
    return absl::InvalidArgumentError(
        absl::StrCat("ground truth: frames [", first_frame, ", ", last_frame, ") are empty"));
  }
  if (frame_step < 1) {
    return absl::InvalidArgumentError(absl::StrCat("ground truth: frame step ", frame_step, " is not 1 or more"));
  }
  if (uv_size < 16 || uv_size > 16384) {
    return absl::InvalidArgumentError(absl::StrCat("ground truth: uv size ", uv_size, " is not in 16..16384"));
  }
  return absl::OkStatus();
}

absl::Status WriteGroundTruth(const SimScene& scene, const std::string& dir, const GroundTruthOptions& options) {
  // OpenCV reads OpenEXR only when asked to (a guard against untrusted files); these are our own.
  setenv("OPENCV_IO_ENABLE_OPENEXR", "1", 0);
  if (auto st = options.Validate(); !st.ok()) return st;
  std::vector<int> cameras;
  if (options.cameras.empty()) {
    for (int i = 0; i < scene.rig().cameras_size(); ++i) cameras.push_back(i);
  } else {
    for (const std::string& id : options.cameras) {
      const int i = scene.CameraIndex(id);
      if (i < 0) return absl::NotFoundError(absl::StrCat("ground truth: camera \"", id, "\" is not in the rig"));
      cameras.push_back(i);
    }
  }
  // Each camera's rays undistorted once for every frame (a few MB a camera at the simulator's usual scales).
  std::map<int, CameraRays> rays_of;
  for (int index : cameras) rays_of.emplace(index, CameraRays(scene.camera(index), size_t{16} << 20));
  const int64_t frames = (options.last_frame - options.first_frame + options.frame_step - 1) / options.frame_step;
  const int total = static_cast<int>(frames * static_cast<int64_t>(cameras.size()));
  int done = 0;
  {
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
    STAGE_RETURN_IF_ERROR(WriteCameraCalibration(dir + "/cameras.json", scene.true_cameras()));
  }
  for (int64_t frame = options.first_frame; frame < options.last_frame; frame += options.frame_step) {
    const std::string frame_dir = absl::StrFormat("%s/frame-%06d", dir, frame - options.name_offset);
    std::error_code ec;
    fs::create_directories(frame_dir, ec);
    if (ec) return absl::UnavailableError(absl::StrCat(frame_dir, ": ", ec.message()));
    const HeadPose pose = scene.PoseAt(frame);
    nlohmann::json j;
    j["frame"] = frame;  // the world's
    j["dir_frame"] = frame - options.name_offset;
    j["time_s"] = (static_cast<double>(frame) + 0.5) * static_cast<double>(scene.schedule().patterns_size()) /
                  scene.base().slot_rate_hz();
    j["subject"] = scene.rig().sim().subject().kind();
    if (scene.head() != nullptr) {
      for (int e = 0; e < kExpressionCount; ++e) j["expression"][ExpressionName(e)] = pose.expression[e];
    }
    j["rotation_deg"] = {
        {"yaw", pose.rotation_deg.x()}, {"pitch", pose.rotation_deg.y()}, {"roll", pose.rotation_deg.z()}};
    j["translation_mm"] = {pose.translation_mm.x(), pose.translation_mm.y(), pose.translation_mm.z()};
    if (const RiggedModel* model = scene.model(); model != nullptr) {
      // The head's frame to the stage's, as the fit writes it (row-major 4 x 4, mm): PosedMesh's turn about the
      // pivot, then the translation.
      const Eigen::Matrix3f r = PoseRotation(pose);
      const Eigen::Vector3f t = model->pivot() + pose.translation_mm - r * model->pivot();
      nlohmann::json m = nlohmann::json::array();
      for (int row = 0; row < 4; ++row) {
        for (int col = 0; col < 4; ++col)
          m.push_back(row < 3 ? (col < 3 ? r(row, col) : t[row]) : (col < 3 ? 0.f : 1.f));
      }
      j["stage_from_head"] = m;
    }
    if (const std::string sequence = scene.SequenceAt(frame); !sequence.empty()) j["sequence"] = sequence;
    if (const BoardModel* board = scene.board(); board != nullptr) {
      // The ChArUco corners where the board is, by OpenCV's corner id.
      nlohmann::json corners = nlohmann::json::array();
      for (const Eigen::Vector3f& c : board->CornersAt(pose)) corners.push_back({c.x(), c.y(), c.z()});
      const v1::SimBoard& config = scene.rig().sim().subject().board();
      j["board"] = {{"squares_x", config.squares_x()},   {"squares_y", config.squares_y()},
                    {"square_mm", config.square_mm()},   {"marker_mm", config.marker_mm()},
                    {"dictionary", config.dictionary()}, {"corners_mm", corners}};
    }
    {
      std::ofstream out(frame_dir + "/pose.json");
      out << j.dump(2) << "\n";
      if (!out) return absl::UnavailableError(absl::StrCat(frame_dir, "/pose.json: cannot write"));
    }
    if (scene.model() != nullptr) {
      const TriangleMesh mesh = scene.model()->PosedMesh(pose);
      if (options.meshes) {
        STAGE_RETURN_IF_ERROR(WriteObj(frame_dir + "/mesh.obj", mesh,
                                       "FaStage simulator ground truth: posed subject, stage frame, millimetres"));
      }
      // Row 0 of the image is v = 1 (the crown's side), as textures are stored (uv_raster.h).
      STAGE_RETURN_IF_ERROR(
          WriteRgba(frame_dir + "/uv_position.exr", UvPositionMap(mesh, options.uv_size), options.uv_size));
      if (options.uv_textures) {
        const UvMaterialMaps maps = UvMaterials(*scene.model(), pose, options.uv_size);
        STAGE_RETURN_IF_ERROR(WriteRgba(frame_dir + "/uv_albedo.exr", maps.albedo, options.uv_size));
        STAGE_RETURN_IF_ERROR(WriteRgba(frame_dir + "/uv_material.exr", maps.material, options.uv_size));
        STAGE_RETURN_IF_ERROR(WriteRgba(frame_dir + "/uv_normal.exr", maps.normal, options.uv_size));
      }
    }
    if (!options.camera_maps) {
      done += static_cast<int>(cameras.size());
      if (options.progress) options.progress(done, total);
      continue;
    }
    auto subject = scene.SubjectAt(frame);
    // A pixel integrates n x n rays (sim.supersample): its truth describes that area, as its value does (the mean
    // normal normalized, the mean material; the albedo over sim.texture_samples rays); the depth is its centre's.
    const int n = std::max(1, static_cast<int>(scene.rig().sim().supersample()));
    for (int index : cameras) {
      const CameraModel& camera = scene.camera(index);
      CameraRays& camera_rays = rays_of.at(index);
      const std::vector<Hit> hits = TracePixels(camera_rays, *subject);
      const int texture_n = static_cast<int>(scene.rig().sim().texture_samples());
      const AreaAlbedo area = texture_n > n ? TraceAreaAlbedo(camera_rays, *subject, texture_n) : AreaAlbedo{};
      std::vector<std::vector<Hit>> rays;
      if (n > 1) {
        for (int sy = 0; sy < n; ++sy) {
          for (int sx = 0; sx < n; ++sx) {
            rays.push_back(TracePixels(camera_rays, *subject, 0, (sx + 0.5) / n - 0.5, (sy + 0.5) / n - 0.5));
          }
        }
      }
      const int w = camera.width(), h = camera.height();
      cv::Mat depth(h, w, CV_32F, 0.0f), nw(h, w, CV_32FC3, cv::Scalar::all(0)), nc(h, w, CV_32FC3, cv::Scalar::all(0));
      cv::Mat albedo(h, w, CV_32FC3, cv::Scalar::all(0)), spec(h, w, CV_32F, 0.0f), rough(h, w, CV_32F, 0.0f);
      cv::Mat mask(h, w, CV_8U, cv::Scalar(0));
      const Eigen::Matrix3f rot = camera.rotation().cast<float>();
      const Eigen::Vector3f center = camera.position().cast<float>();
      for (size_t i = 0; i < hits.size(); ++i) {
        Hit hit = hits[i];
        int covered = hit.hit ? 1 : 0, total_rays = 1;
        if (n > 1) {
          Eigen::Vector3f normal = Eigen::Vector3f::Zero(), a = Eigen::Vector3f::Zero();
          float sp = 0, ro = 0;
          covered = 0;
          total_rays = n * n;
          for (const std::vector<Hit>& r : rays) {
            if (!r[i].hit) continue;
            if (!hit.hit) hit = r[i];
            normal += r[i].normal;
            a += r[i].material.albedo;
            sp += r[i].material.specular;
            ro += r[i].material.roughness;
            ++covered;
          }
          if (covered > 0) {
            hit.normal = normal.norm() > 0 ? Eigen::Vector3f(normal.normalized()) : hit.normal;
            hit.material.albedo = a / static_cast<float>(covered);
            hit.material.specular = sp / static_cast<float>(covered);
            hit.material.roughness = ro / static_cast<float>(covered);
          }
        }
        if (covered == 0) continue;
        if (!area.rays.empty() && area.rays[i] > 0) hit.material.albedo = area.albedo[i];
        const int y = static_cast<int>(i) / w, x = static_cast<int>(i) % w;
        depth.at<float>(y, x) = (rot * (hit.point - center)).z();
        nw.at<cv::Vec3f>(y, x) = Bgr(hit.normal);
        nc.at<cv::Vec3f>(y, x) = Bgr(rot * hit.normal);
        albedo.at<cv::Vec3f>(y, x) = Bgr(hit.material.albedo);
        spec.at<float>(y, x) = hit.material.specular;
        rough.at<float>(y, x) = hit.material.roughness;
        mask.at<uint8_t>(y, x) = covered == total_rays ? 255 : 128;
      }
      const std::string cam_dir = frame_dir + "/" + scene.rig().cameras(index).id();
      fs::create_directories(cam_dir, ec);
      if (ec) return absl::UnavailableError(absl::StrCat(cam_dir, ": ", ec.message()));
      for (const auto& [name, image] : std::vector<std::pair<std::string, cv::Mat>>{{"depth.exr", depth},
                                                                                    {"normal_world.exr", nw},
                                                                                    {"normal_camera.exr", nc},
                                                                                    {"albedo.exr", albedo},
                                                                                    {"specular.exr", spec},
                                                                                    {"roughness.exr", rough},
                                                                                    {"mask.png", mask}}) {
        if (auto s = Write(cam_dir + "/" + name, image); !s.ok()) return s;
      }
      if (options.progress) options.progress(++done, total);
    }
  }
  return absl::OkStatus();
}

}  // namespace stage::sim
