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
  if (absl::Status s = node_->Arm(*request); !s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::Disarm(grpc::ServerContext*, const v1::DisarmLightRequest* request,
                                  v1::LightStats* response) {
  if (absl::Status s = node_->Disarm(request->take_id()); !s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::Blackout(grpc::ServerContext*, const v1::BlackoutRequest* request,
                                    v1::LightStats* response) {
  absl::Status s = node_->Blackout(request->reason().empty() ? "blackout requested" : request->reason());
  if (!s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::ResetBlackout(grpc::ServerContext*, const v1::ResetBlackoutRequest*,
                                         v1::LightStats* response) {
  if (absl::Status s = node_->ResetBlackout(); !s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::Heartbeat(grpc::ServerContext*, const v1::HeartbeatRequest* request,
                                     v1::LightStats* response) {
  node_->Heartbeat(request->take_id());
  *response = node_->Stats();
  return grpc::Status::OK;
}

namespace {

grpc::Status Reply(absl::StatusOr<v1::SlotClockRun> run, v1::SlotClockRun* response) {
  if (!run.ok()) return ToGrpcStatus(run.status());
  *response = *std::move(run);
  return grpc::Status::OK;
}

}  // namespace

grpc::Status LightService::RunSlotClock(grpc::ServerContext*, const v1::SlotClockRunRequest* request,
                                        v1::SlotClockRun* response) {
  return Reply(node_->RunSlotClock(*request), response);
}

grpc::Status LightService::EndSlotClock(grpc::ServerContext*, const v1::EndSlotClockRequest* request,
                                        v1::SlotClockRun* response) {
  return Reply(node_->EndSlotClock(request->align_slots()), response);
}

grpc::Status LightService::GetSlotClock(grpc::ServerContext*, const v1::GetSlotClockRequest*,
                                        v1::SlotClockRun* response) {
  return Reply(node_->GetSlotClock(), response);
}

grpc::Status LightService::StartTable(grpc::ServerContext*, const v1::StartTableRequest* request,
                                      v1::LightStats* response) {
  if (absl::Status s = node_->StartTable(request->take_id(), request->first_edge_ns()); !s.ok()) return ToGrpcStatus(s);
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status LightService::GetClockInput(grpc::ServerContext*, const v1::GetClockInputRequest*,
                                         v1::ClockInput* response) {
  auto in = node_->ClockInput();
  if (!in.ok()) return ToGrpcStatus(in.status());
  *response = *std::move(in);
  return grpc::Status::OK;
}

}  // namespace stage::light
