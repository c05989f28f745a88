// gRPC StageController service: stage status from the health monitor, and the timing verifier and waveform export on
// the live rig.
#pragma once

#include <mutex>
#include <string>
#include <thread>

#include "capture.h"
#include "device_monitor.h"
#include "health_monitor.h"
#include "stage/common/rig.h"
#include "stage/v1/camera_node.pb.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/rig.pb.h"
#include "stage/v1/timing.pb.h"

namespace stage::controller {

class ControllerService final : public v1::StageController::Service {
 public:
  // `monitor` is not owned and must outlive the service. The rig's schedule is compiled and verified here, once;
  // its verdict is logged and shown in every status.
  ControllerService(LoadedRig rig, HealthMonitor* monitor);
  ~ControllerService() override;
  // Takes: the take root and the sync generator (capture.h). Without it, Capture, ListTakes and GetTake are
  // FAILED_PRECONDITION.
  absl::Status EnableCapture(CaptureOptions options, CaptureDevices devices);

  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) override;
  grpc::Status GetStageStatus(grpc::ServerContext*, const v1::GetStageStatusRequest*,
                              v1::StageStatus* response) override;
  grpc::Status WatchStageStatus(grpc::ServerContext* context, const v1::WatchStageStatusRequest* request,
                                grpc::ServerWriter<v1::StageStatus>* writer) override;
  grpc::Status CheckTiming(grpc::ServerContext*, const v1::TimingQuery* request, v1::TimingReport* response) override;
  grpc::Status ExportTiming(grpc::ServerContext*, const v1::TimingExportRequest* request,
                            v1::TimingExport* response) override;
  grpc::Status RehearseTriggers(grpc::ServerContext* context, const v1::RehearseTriggersRequest* request,
                                v1::TriggerRehearsal* response) override;
  grpc::Status Capture(grpc::ServerContext* context, const v1::CaptureRequest* request,
                       grpc::ServerWriter<v1::CaptureEvent>* writer) override;
  grpc::Status WatchTake(grpc::ServerContext* context, const v1::WatchTakeRequest* request,
                         grpc::ServerWriter<v1::CaptureEvent>* writer) override;
  grpc::Status GetLedger(grpc::ServerContext*, const v1::GetLedgerRequest* request, v1::LedgerPage* response) override;
  grpc::Status ListTakes(grpc::ServerContext*, const v1::ListTakesRequest*, v1::TakeList* response) override;
  grpc::Status GetTake(grpc::ServerContext*, const v1::GetTakeRequest* request, v1::TakeSummary* response) override;
  grpc::Status Arm(grpc::ServerContext* context, const v1::CaptureRequest* request,
                   grpc::ServerWriter<v1::CaptureEvent>* writer) override;
  grpc::Status Pause(grpc::ServerContext*, const v1::SessionRequest*, v1::SessionReply* response) override;
  grpc::Status Resume(grpc::ServerContext*, const v1::SessionRequest*, v1::SessionReply* response) override;
  grpc::Status Abort(grpc::ServerContext*, const v1::SessionRequest*, v1::SessionReply* response) override;
  grpc::Status GetPreview(grpc::ServerContext*, const v1::ControllerPreviewRequest* request,
                          v1::Preview* response) override;
  grpc::Status EmergencyStop(grpc::ServerContext*, const v1::EmergencyStopRequest* request,
                             v1::EmergencyStopReply* response) override;
  grpc::Status ResetEmergencyStop(grpc::ServerContext*, const v1::ResetEmergencyStopRequest*,
                                  v1::EmergencyStopReply* response) override;
  grpc::Status ProcessTake(grpc::ServerContext* context, const v1::ProcessTakeRequest* request,
                           grpc::ServerWriter<v1::ProcessingProgress>* writer) override;

  // Shows what `devices` last read of the nodes' devices in every status (StageStatus.devices). Not owned; it must
  // outlive the service. Without it the status has no devices.
  void ShowDevices(const DeviceMonitor* devices) { devices_ = devices; }

  v1::StageStatus Status() const;

  // The live rig's verifier report (the schedule inside), or empty with the error when it could not be compiled.
  const v1::TimingReport& timing() const { return timing_; }

 private:
  LoadedRig rig_;
  v1::TimingReport timing_;
  std::string stage_id_;
  std::string stage_name_;
  std::string rig_hash_;
  HealthMonitor* monitor_;
  const DeviceMonitor* devices_ = nullptr;
  std::unique_ptr<controller::EmergencyStop> estop_;
  std::mutex estop_abort_mutex_;
  std::thread estop_abort_;  // aborts the take after an emergency stop has answered
  std::unique_ptr<Capturer> capturer_;
};

// What a node needs to convert controller times to its clock, from the controller's measurement of it.
v1::ClockMapping ClockMappingOf(const v1::ClockStatus& clock);

// Targets to poll: every camera, light node and processing worker of the rig, in rig order. With the rig's schedule,
// each gets the clock uncertainty its trigger mode tolerates: a camera on scheduled software triggers half its late
// slack (at least 10 us); other cameras and light nodes a quarter slot (frames and measured edges are matched to slots
// by time); workers none.
std::vector<NodeTarget> TargetsFromRig(const v1::RigConfig& rig, const v1::Schedule* schedule = nullptr);

}  // namespace stage::controller
