// A take rendered straight from the scene: see rendered_take.h.
#include "stage/sim/rendered_take.h"

#include <google/protobuf/util/json_util.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "stage/common/file_util.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/common/version.h"
#include "stage/sim/ground_truth.h"
#include "stage/storage/frame_file.h"

namespace stage::sim {
namespace {

namespace fs = std::filesystem;

storage::FrameFileInfo FileInfo(const SimScene& scene, int camera, const std::string& take_id, const RawImage& raw) {
  const v1::CameraConfig& config = scene.rig().cameras(camera);
  storage::FrameFileInfo info;
  info.camera_id = config.id();
  info.take_id = take_id;
  info.width = static_cast<uint32_t>(raw.width);
  info.height = static_cast<uint32_t>(raw.height);
  info.pixel_format = PixelFormatName(config.pixel_format());
  info.bytes_per_pixel = raw.bits > 8 ? 2 : 1;
  info.exposure_us = config.exposure_us();
  info.gain_db = config.gain_db();
  nlohmann::json patterns = nlohmann::json::array();
  for (const v1::SchedulePattern& p : scene.schedule().patterns()) {
    patterns.push_back({{"index", p.index()},
                        {"name", p.name()},
                        {"polarization", p.polarization() == v1::POLARIZATION_PARALLEL ? "parallel" : "cross"}});
  }
  info.patterns_json = patterns.dump();
  v1::CameraConfig calibration;
  *calibration.mutable_intrinsics() = config.intrinsics();
  *calibration.mutable_pose() = config.pose();
  google::protobuf::util::JsonPrintOptions o;
  o.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(calibration, &info.calibration_json, o);
  return info;
}

absl::Status WriteTakeFile(const SimScene& scene, const std::string& dir, const std::string& take_id) {
  std::string rig;
  google::protobuf::util::JsonPrintOptions o;
  o.preserve_proto_field_names = true;
  if (!google::protobuf::util::MessageToJsonString(scene.rig(), &rig, o).ok()) {
    return absl::InternalError("rendered take: the rig does not print as JSON");
  }
  nlohmann::json take = {{"format", "fastage-take-1"},
                         {"take_id", take_id},
                         {"state", "rendered"},
                         {"software_version", std::string(kVersion)},
                         {"rig", nlohmann::json::parse(rig)}};
  return WriteFileAtomically(dir + "/take.json", take.dump(2) + "\n");
}

}  // namespace

absl::Status RenderedTakeOptions::Validate() const {
  if (last_frame <= first_frame || first_frame < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("rendered take: frames [", first_frame, ", ", last_frame, ") are empty"));
  }
  if (frame_step < 1) return absl::InvalidArgumentError(absl::StrCat("rendered take: frame step ", frame_step));
  if (uv_size < 16 || uv_size > 16384) {
    return absl::InvalidArgumentError(absl::StrCat("rendered take: uv size ", uv_size, " is not in 16..16384"));
  }
  if (threads < 0) return absl::InvalidArgumentError(absl::StrCat("rendered take: threads ", threads));
  return absl::OkStatus();
}

absl::Status WriteRenderedTake(std::shared_ptr<const SimScene> scene, const std::string& dir,
                               const RenderedTakeOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (fs::exists(dir + "/take.json")) return absl::AlreadyExistsError(absl::StrCat(dir, ": holds a take already"));
  // A render cut short leaves frame files and no take file: begun again, it starts over.
  std::error_code removed;
  fs::remove_all(dir + "/cameras", removed);
  std::vector<int> cameras;
  if (options.cameras.empty()) {
    for (int i = 0; i < scene->rig().cameras_size(); ++i) {
      if (scene->rig().cameras(i).role() == v1::CAMERA_ROLE_MACHINE_VISION) cameras.push_back(i);
    }
  } else {
    for (const std::string& id : options.cameras) {
      const int i = scene->CameraIndex(id);
      if (i < 0) return absl::NotFoundError(absl::StrCat("rendered take: camera \"", id, "\" is not in the rig"));
      cameras.push_back(i);
    }
  }
  if (cameras.empty()) return absl::InvalidArgumentError("rendered take: no camera to render");
  std::vector<int> patterns;
  if (options.full_lit_only) {
    patterns = scene->FullOnPatterns();
    if (patterns.empty()) return absl::FailedPreconditionError("rendered take: the schedule has no full-on pattern");
  } else {
    for (int p = 0; p < scene->schedule().patterns_size(); ++p) patterns.push_back(p);
  }
  std::error_code ec;
  fs::create_directories(dir + "/cameras", ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, "/cameras: ", ec.message()));
  fs::path normal = fs::path(dir).lexically_normal();
  if (normal.filename().empty()) normal = normal.parent_path();  // "takes/a/" names take "a"
  const std::string take_id = normal.filename().string();

  const int64_t cycle = scene->schedule().patterns_size();
  const int64_t frames = (options.last_frame - options.first_frame + options.frame_step - 1) / options.frame_step;
  const int64_t total = frames * static_cast<int64_t>(cameras.size());
  int64_t done = 0;
  for (int camera : cameras) {
    CameraRenderer renderer(scene, camera, options.threads);
    // Each pose is rendered under these patterns alone: their sums per pixel, not a response per unit (the bulk of the
    // memory and of the time at full scale).
    std::vector<EmitterLevels> exposures;
    for (int p : patterns) exposures.push_back(scene->PatternLevels(p));
    renderer.ExpectOnly(std::move(exposures));
    renderer.KeepRays(size_t{4} << 30);  // every pose has the same rays: undistorted once
    const double exposure_s = scene->rig().cameras(camera).exposure_us() * 1e-6;
    const std::string path = absl::StrCat(dir, "/cameras/", scene->rig().cameras(camera).id(), ".h5");
    std::unique_ptr<storage::FrameFileWriter> writer;
    uint64_t counter = 0;
    for (int64_t frame = options.first_frame; frame < options.last_frame; frame += options.frame_step) {
      for (int p : patterns) {
        const RawImage raw = renderer.Render(scene->PatternLevels(p), exposure_s, counter, frame);
        if (writer == nullptr) {
          STAGE_ASSIGN_OR_RETURN(writer,
                                 storage::FrameFileWriter::Create(path, FileInfo(*scene, camera, take_id, raw)));
        }
        storage::FrameRecord record;
        record.frame_id = counter++;
        record.slot = frame * cycle + p;
        record.pattern = p;
        record.status = storage::FrameStatus::kOk;
        const std::vector<uint8_t> bytes = PackRaw(raw, PixelFormatName(scene->rig().cameras(camera).pixel_format()));
        STAGE_RETURN_IF_ERROR(writer->Append(record, bytes));
      }
      if (options.progress) options.progress(++done, total);
    }
    STAGE_RETURN_IF_ERROR(writer->Close());
  }
  GroundTruthOptions truth;
  truth.first_frame = options.first_frame;
  truth.last_frame = options.last_frame;
  truth.frame_step = options.frame_step;
  truth.uv_size = options.uv_size;
  truth.camera_maps = options.truth_camera_maps;
  truth.meshes = options.truth_meshes;
  truth.uv_textures = options.truth_textures;
  for (int camera : cameras) truth.cameras.push_back(scene->rig().cameras(camera).id());
  STAGE_RETURN_IF_ERROR(WriteGroundTruth(*scene, dir + "/ground_truth", truth));
  // Last: a render that failed half way leaves no take file, and can be run again into the same directory.
  return WriteTakeFile(*scene, dir, take_id);
}

}  // namespace stage::sim
