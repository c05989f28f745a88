// gRPC LightNode service.
#include "light_service.h"

namespace stage::light {

grpc::Status LightService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = node_->Info();
  return grpc::Status::OK;
}

grpc::Status LightService::GetStats(grpc::ServerContext*, const v1::GetLightStatsRequest*, v1::LightStats* response) {
  *response = node_->Stats();
  return grpc::Status::OK;
}

}  // namespace stage::light
