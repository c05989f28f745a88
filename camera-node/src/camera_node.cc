// Camera node logic.
#include "camera_node.h"

#include "absl/strings/str_cat.h"
#include "stage/common/node_info.h"
#include "stage/common/status.h"

namespace stage::camera {

std::string PixelFormatName(v1::PixelFormat format) {
  switch (format) {
    case v1::PIXEL_FORMAT_MONO8:
      return "Mono8";
    case v1::PIXEL_FORMAT_MONO12:
      return "Mono12";
    case v1::PIXEL_FORMAT_MONO16:
      return "Mono16";
    case v1::PIXEL_FORMAT_BAYER_RG8:
      return "BayerRG8";
    case v1::PIXEL_FORMAT_BAYER_GR8:
      return "BayerGR8";
    case v1::PIXEL_FORMAT_BAYER_GB8:
      return "BayerGB8";
    case v1::PIXEL_FORMAT_BAYER_BG8:
      return "BayerBG8";
    case v1::PIXEL_FORMAT_BAYER_RG12:
      return "BayerRG12";
    case v1::PIXEL_FORMAT_BAYER_RG16:
      return "BayerRG16";
    case v1::PIXEL_FORMAT_RGB8:
      return "RGB8";
    default:
      return "";
  }
}

absl::StatusOr<CameraSettings> SettingsFromConfig(const v1::CameraConfig& config) {
  CameraSettings s;
  s.width = config.width();
  s.height = config.height();
  s.pixel_format = PixelFormatName(config.pixel_format());
  if (s.pixel_format.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(), "\": pixel_format is not set"));
  }
  s.frame_rate_hz = config.frame_rate_hz();
  s.exposure_us = config.exposure_us();
  s.gain_db = config.gain_db();
  switch (config.trigger().source()) {
    case v1::TRIGGER_SOURCE_HARDWARE_LINE:
      s.trigger = TriggerMode::kHardware;
      break;
    case v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE:
      s.trigger = TriggerMode::kSoftware;
      break;
    case v1::TRIGGER_SOURCE_FREE_RUN:
      s.trigger = TriggerMode::kFreeRun;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(), "\": trigger.source is not set"));
  }
  return s;
}

absl::StatusOr<std::unique_ptr<CameraNode>> CameraNode::Create(const v1::CameraConfig& config,
                                                               std::unique_ptr<CameraDevice> device,
                                                               std::string rig_hash) {
  STAGE_ASSIGN_OR_RETURN(CameraSettings settings, SettingsFromConfig(config));
  STAGE_RETURN_IF_ERROR(Annotate(device->Configure(settings), absl::StrCat("camera \"", config.id(), "\"")));
  return std::unique_ptr<CameraNode>(new CameraNode(config, std::move(device), std::move(rig_hash)));
}

CameraNode::CameraNode(v1::CameraConfig config, std::unique_ptr<CameraDevice> device, std::string rig_hash)
    : config_(std::move(config)), device_(std::move(device)), rig_hash_(std::move(rig_hash)) {}

CameraNode::~CameraNode() { (void)device_->Stop(); }

v1::NodeInfo CameraNode::Info() const {
  std::string role = config_.role() == v1::CAMERA_ROLE_HIGH_SPEED ? "high-speed" : "machine-vision";
  return MakeNodeInfo(config_.id(), v1::NODE_KIND_CAMERA, role, device_->Describe().backend, rig_hash_);
}

v1::CameraStats CameraNode::Stats() const {
  v1::CameraStats stats;
  stats.set_frames_completed(frames_completed_.load());
  stats.set_bytes_written(0);  // nothing is recorded before the capture issue
  return stats;
}

void CameraNode::OnFrame(std::shared_ptr<const Frame> frame) {
  frames_completed_.fetch_add(1);
  bytes_received_.fetch_add(frame->data.size());
}

}  // namespace stage::camera
