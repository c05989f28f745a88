// The camera node's logic: owns the device, counts what it delivers, answers for the service.
#pragma once

#include <atomic>
#include <memory>
#include <mutex>
#include <string>

#include "absl/status/statusor.h"
#include "recorder.h"
#include "stage/camera/camera_device.h"
#include "stage/common/metrics.h"
#include "stage/v1/camera_node.pb.h"
#include "stage/v1/node.pb.h"
#include "stage/v1/rig.pb.h"

namespace stage::camera {

// Settings for the device from the rig's camera entry. InvalidArgument names the camera and the field.
absl::StatusOr<CameraSettings> SettingsFromConfig(const v1::CameraConfig& config);

// One stream of scheduled software triggers (CameraNode.StreamTriggers): converts controller times to this node's
// clock with the controller's measurement and fires each through a TriggerScheduler at its time.
class TriggerSession {
 public:
  virtual ~TriggerSession() = default;
  // A trigger for `slot` at `time_ns` after the take's T0 (controller time).
  virtual void Submit(int64_t slot, int64_t time_ns) = 0;
  virtual void UpdateClock(const v1::ClockMapping& clock) = 0;
  // Waits for every trigger to be fired or counted, stops, and reports. `error` (if any) is why the stream ended.
  virtual v1::TriggerReport Finish(const std::string& error) = 0;
};

class CameraNode : public FrameSink {
 public:
  // Configures `device` from `config`; fails with the camera id in the message.
  static absl::StatusOr<std::unique_ptr<CameraNode>> Create(const v1::CameraConfig& config,
                                                            std::unique_ptr<CameraDevice> device, std::string rig_hash);
  ~CameraNode() override;

  v1::NodeInfo Info() const;
  v1::CameraStats Stats() const;

  // FrameSink: counts frames and hands them to the armed take's recorder.
  void OnFrame(std::shared_ptr<const Frame> frame) override;
  void OnFrameLost() override;

  // A take (CameraNode.Arm / Finish in camera_node.proto).
  absl::StatusOr<v1::ArmCameraResponse> Arm(const v1::ArmCameraRequest& request);
  absl::StatusOr<v1::CameraTakeReport> Finish(const v1::FinishCameraRequest& request);
  absl::StatusOr<v1::ArmCameraResponse> UpdateTake(const v1::UpdateTakeRequest& request);
  absl::StatusOr<v1::Preview> GetPreview(const v1::GetPreviewRequest& request) const;

  // Starts a stream of scheduled software triggers. FailedPrecondition when the camera's trigger source is not
  // scheduled-software or a stream is already running. The device is started for the stream if it was not.
  absl::StatusOr<std::unique_ptr<TriggerSession>> BeginTriggerStream(const v1::TriggerStreamHeader& header);

  CameraDevice& device() { return *device_; }

 private:
  CameraNode(v1::CameraConfig config, std::unique_ptr<CameraDevice> device, std::string rig_hash);
  // The recorder of take `take_id`; NotFound when that take is not armed here.
  absl::StatusOr<std::shared_ptr<TakeRecorder>> ArmedRecorder(const std::string& take_id) const;
  v1::CameraConfig config_;
  std::unique_ptr<CameraDevice> device_;
  std::string rig_hash_;
  std::atomic<uint64_t> frames_completed_{0};
  std::atomic<uint64_t> bytes_received_{0};
  std::atomic<bool> streaming_{false};
  // The counter of the last frame delivered (the next take's first exposure follows it); -1 before any.
  std::atomic<int64_t> last_frame_id_{-1};
  mutable std::mutex take_mutex_;
  std::string take_id_;                     // guarded by take_mutex_
  std::shared_ptr<TakeRecorder> recorder_;  // guarded by take_mutex_; frames go to it while set
  // The device's link as the take was armed (outages during the take are told to its recorder); take_mutex_.
  uint64_t link_losses_at_arm_ = 0;
  bool link_down_at_arm_ = false;
  // The take being finished (its burst offload), for Stats; guarded by take_mutex_.
  std::shared_ptr<TakeRecorder> finishing_;
  std::string finishing_id_;
  // The node's families for the metrics, from Stats(); the registration goes first when the node does.
  void CollectMetrics(metrics::Writer& w) const;
  metrics::Registration metrics_;
  friend class TriggerSessionImpl;
};

}  // namespace stage::camera
