// gRPC CameraNode service.
#include "camera_service.h"

namespace stage::camera {

grpc::Status CameraService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = node_->Info();
  return grpc::Status::OK;
}

grpc::Status CameraService::GetStats(grpc::ServerContext*, const v1::GetStatsRequest*, v1::CameraStats* response) {
  *response = node_->Stats();
  return grpc::Status::OK;
}

}  // namespace stage::camera
