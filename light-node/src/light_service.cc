// gRPC LightNode service.
#include "light_service.h"

#include "stage/common/grpc_status.h"

namespace stage::light {

grpc::Status LightService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = node_->Info();
  return grpc::Status::OK;
}

grpc::Status LightService::GetStats(grpc::ServerContext*, const v1::GetLightStatsRequest*, v1::LightStats* response) {
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::Arm(grpc::ServerContext*, const v1::ArmLightRequest* request, v1::LightStats* response) {
  if (absl::Status s = node_->Arm(request->take_id(), request->table()); !s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::Disarm(grpc::ServerContext*, const v1::DisarmLightRequest* request,
                                  v1::LightStats* response) {
  if (absl::Status s = node_->Disarm(request->take_id()); !s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

}  // namespace stage::light
