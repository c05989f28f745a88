// A GigE Vision (or USB3 Vision) camera through Aravis, behind the CameraDevice interface. Only
// aravis_camera_device.cc includes Aravis.
//
// Opened by serial number, user id, Aravis device id or IP address. Configure() sets the standard features in SFNC
// category order (image format, acquisition and trigger, analog, transport) and then the rig's extra features, reading
// every value back; a feature the camera lacks or refuses gives an error naming the camera, the feature and the value.
// Frames stream into a pool of buffers that are lent to the node (zero copy) and return to the pool when the last
// reference to the frame goes. A buffer that arrives incomplete (packets lost, timeout) is delivered marked, never
// dropped. When control of the camera is lost (heartbeat, cable, power), the device keeps going: it reconnects with
// backoff, restores the settings, restarts the stream if it was running, and reports the outage in Stats().
#pragma once

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/camera/camera_device.h"

namespace stage::camera {

struct AravisCameraInfo {
  std::string id;  // Aravis's device id
  std::string vendor;
  std::string model;
  std::string serial;
  std::string address;   // IP address (GigE Vision) or bus position (USB3)
  std::string protocol;  // "GigEVision", "USB3Vision"
};

// The cameras Aravis finds now (GigE Vision discovery on every interface, USB3 Vision).
std::vector<AravisCameraInfo> ListAravisCameras();

class AravisCameraDevice final : public CameraDevice {
 public:
  // Opens `device` (serial, user id, device id or IP address) for the rig's camera `camera_id` (named in errors).
  // Unavailable, listing the cameras that were found, when it cannot be opened.
  static absl::StatusOr<std::unique_ptr<AravisCameraDevice>> Open(const std::string& camera_id,
                                                                  const std::string& device);
  ~AravisCameraDevice() override;

  CameraDescription Describe() const override;
  absl::Status Configure(const CameraSettings& settings) override;
  absl::Status Start(FrameSink* sink) override;
  absl::Status Stop() override;
  absl::Status Trigger() override;
  DeviceStats Stats() const override;

  // Every feature the last Configure() set and the value the camera read back, in the order they were set.
  std::vector<std::pair<std::string, std::string>> ReadBack() const;

  struct Impl;

 private:
  explicit AravisCameraDevice(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stage::camera
