// gRPC CameraNode service: translates messages to CameraNode calls, nothing more.
#pragma once

#include "camera_node.h"
#include "stage/v1/camera_node.grpc.pb.h"

namespace stage::camera {

class CameraService final : public v1::CameraNode::Service {
 public:
  explicit CameraService(CameraNode* node) : node_(node) {}
  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) override;
  grpc::Status GetStats(grpc::ServerContext*, const v1::GetStatsRequest*, v1::CameraStats* response) override;
  grpc::Status StreamTriggers(grpc::ServerContext* context, grpc::ServerReader<v1::TriggerStreamMessage>* reader,
                              v1::TriggerReport* response) override;
  grpc::Status Arm(grpc::ServerContext*, const v1::ArmCameraRequest* request, v1::ArmCameraResponse* response) override;
  grpc::Status Finish(grpc::ServerContext*, const v1::FinishCameraRequest* request,
                      v1::CameraTakeReport* response) override;
  grpc::Status UpdateTake(grpc::ServerContext*, const v1::UpdateTakeRequest* request,
                          v1::ArmCameraResponse* response) override;
  grpc::Status GetPreview(grpc::ServerContext*, const v1::GetPreviewRequest* request, v1::Preview* response) override;

 private:
  CameraNode* node_;
};

}  // namespace stage::camera
