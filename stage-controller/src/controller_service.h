// gRPC StageController service: stage status from the health monitor, nothing more (yet).
#pragma once

#include <string>

#include "health_monitor.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/rig.pb.h"

namespace stage::controller {

class ControllerService final : public v1::StageController::Service {
 public:
  // `monitor` is not owned and must outlive the service.
  ControllerService(const v1::RigConfig& rig, HealthMonitor* monitor);

  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) override;
  grpc::Status GetStageStatus(grpc::ServerContext*, const v1::GetStageStatusRequest*,
                              v1::StageStatus* response) override;
  grpc::Status WatchStageStatus(grpc::ServerContext* context, const v1::WatchStageStatusRequest* request,
                                grpc::ServerWriter<v1::StageStatus>* writer) override;

  v1::StageStatus Status() const;

 private:
  std::string stage_id_;
  std::string stage_name_;
  std::string rig_hash_;
  HealthMonitor* monitor_;
};

// Targets to poll: every camera, light node and processing worker of the rig, in rig order.
std::vector<NodeTarget> TargetsFromRig(const v1::RigConfig& rig);

}  // namespace stage::controller
