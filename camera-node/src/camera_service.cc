// gRPC CameraNode service.
#include "camera_service.h"

#include "stage/common/grpc_status.h"

namespace stage::camera {

grpc::Status CameraService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = node_->Info();
  return grpc::Status::OK;
}

grpc::Status CameraService::GetStats(grpc::ServerContext*, const v1::GetStatsRequest*, v1::CameraStats* response) {
  *response = node_->Stats();
  return grpc::Status::OK;
}

grpc::Status CameraService::StreamTriggers(grpc::ServerContext* context,
                                           grpc::ServerReader<v1::TriggerStreamMessage>* reader,
                                           v1::TriggerReport* response) {
  v1::TriggerStreamMessage message;
  if (!reader->Read(&message) || !message.has_header()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "a trigger stream starts with its header");
  }
  auto session = node_->BeginTriggerStream(message.header());
  if (!session.ok()) return ToGrpcStatus(session.status());
  std::string error;
  while (reader->Read(&message)) {
    if (message.has_trigger()) {
      (*session)->Submit(message.trigger().slot(), message.trigger().time_ns());
    } else if (message.has_batch()) {
      for (const auto& t : message.batch().triggers()) (*session)->Submit(t.slot(), t.time_ns());
    } else if (message.has_clock()) {
      (*session)->UpdateClock(message.clock());
    } else {
      error = "unexpected message in a trigger stream (a second header?)";
      break;
    }
  }
  if (error.empty() && context->IsCancelled()) error = "the controller cancelled the stream";
  *response = (*session)->Finish(error);
  return grpc::Status::OK;
}

grpc::Status CameraService::Arm(grpc::ServerContext*, const v1::ArmCameraRequest* request,
                                v1::ArmCameraResponse* response) {
  auto armed = node_->Arm(*request);
  if (!armed.ok()) return ToGrpcStatus(armed.status());
  *response = std::move(*armed);
  return grpc::Status::OK;
}

grpc::Status CameraService::Finish(grpc::ServerContext*, const v1::FinishCameraRequest* request,
                                   v1::CameraTakeReport* response) {
  auto report = node_->Finish(*request);
  if (!report.ok()) return ToGrpcStatus(report.status());
  *response = std::move(*report);
  return grpc::Status::OK;
}

grpc::Status CameraService::UpdateTake(grpc::ServerContext*, const v1::UpdateTakeRequest* request,
                                       v1::ArmCameraResponse* response) {
  auto updated = node_->UpdateTake(*request);
  if (!updated.ok()) return ToGrpcStatus(updated.status());
  *response = std::move(*updated);
  return grpc::Status::OK;
}

grpc::Status CameraService::GetPreview(grpc::ServerContext*, const v1::GetPreviewRequest* request,
                                       v1::Preview* response) {
  auto preview = node_->GetPreview(*request);
  if (!preview.ok()) return ToGrpcStatus(preview.status());
  *response = std::move(*preview);
  return grpc::Status::OK;
}

}  // namespace stage::camera
