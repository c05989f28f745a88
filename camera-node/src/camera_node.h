// The camera node's logic: owns the device, counts what it delivers, answers for the service.
#pragma once

#include <atomic>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/camera/camera_device.h"
#include "stage/v1/camera_node.pb.h"
#include "stage/v1/node.pb.h"
#include "stage/v1/rig.pb.h"

namespace stage::camera {

// Settings for the device from the rig's camera entry. InvalidArgument names the camera and the field.
absl::StatusOr<CameraSettings> SettingsFromConfig(const v1::CameraConfig& config);

// "Mono8", "BayerRG8", ... for the rig's pixel format enum.
std::string PixelFormatName(v1::PixelFormat format);

class CameraNode : public FrameSink {
 public:
  // Configures `device` from `config`; fails with the camera id in the message.
  static absl::StatusOr<std::unique_ptr<CameraNode>> Create(const v1::CameraConfig& config,
                                                            std::unique_ptr<CameraDevice> device, std::string rig_hash);
  ~CameraNode() override;

  v1::NodeInfo Info() const;
  v1::CameraStats Stats() const;

  // FrameSink: counts frames (recording arrives with the capture issue).
  void OnFrame(std::shared_ptr<const Frame> frame) override;

  CameraDevice& device() { return *device_; }

 private:
  CameraNode(v1::CameraConfig config, std::unique_ptr<CameraDevice> device, std::string rig_hash);
  v1::CameraConfig config_;
  std::unique_ptr<CameraDevice> device_;
  std::string rig_hash_;
  std::atomic<uint64_t> frames_completed_{0};
  std::atomic<uint64_t> bytes_received_{0};
};

}  // namespace stage::camera
