// A simulated triggered camera behind the CameraDevice interface. It keeps a camera's contract (settings checked
// and read back, frames with a frame counter and a device timestamp, delivered on its own thread, triggered by
// line, software or free run). Its image is a test pattern until the simulator's renderer (world, subject, dome)
// feeds it.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>

#include "stage/camera/camera_device.h"
#include "stage/common/clock.h"

namespace stage::sim {

// Bytes per pixel of a supported PFNC pixel format (1 or 2), or nullopt if unsupported.
std::optional<int> SimBytesPerPixel(const std::string& pixel_format);

class SimCameraDevice final : public camera::CameraDevice {
 public:
  // `clock` (not owned, outlives the device) times exposures and stamps frames; `serial` names the device.
  SimCameraDevice(Clock* clock, std::string serial);
  ~SimCameraDevice() override;

  camera::CameraDescription Describe() const override;
  absl::Status Configure(const camera::CameraSettings& settings) override;
  absl::Status Start(camera::FrameSink* sink) override;
  absl::Status Stop() override;
  absl::Status Trigger() override;

  // The settings in force (what a real camera would read back).
  camera::CameraSettings settings() const;

 private:
  void Run();
  std::shared_ptr<camera::Frame> Expose(int64_t start_ns);

  Clock* clock_;
  std::string serial_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  camera::CameraSettings settings_;  // guarded by mutex_
  bool configured_ = false;          // guarded by mutex_
  bool running_ = false;             // guarded by mutex_
  uint64_t pending_triggers_ = 0;    // guarded by mutex_
  uint64_t next_frame_id_ = 0;       // acquisition thread only
  camera::FrameSink* sink_ = nullptr;
  std::thread thread_;
};

}  // namespace stage::sim
