// The world's bus from outside: see world_bus.h.
#include "stage/sim/world_bus.h"

#include <grpcpp/grpcpp.h>

#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"

namespace stage::sim {

WorldBus::WorldBus(const std::string& address, std::string caller)
    : address_(address), caller_(std::move(caller)), world_(v1::SimWorld::NewStub(MakeChannel(address))) {}

absl::StatusOr<v1::WorldRunReply> WorldBus::Run(v1::RunWorldRequest request,
                                                std::chrono::steady_clock::time_point give_up) {
  request.set_requested_by(caller_);
  v1::WorldRunReply run;
  // Planning is a question, and starting the run planned twice starts it once: a world slow to answer is asked again.
  STAGE_RETURN_IF_ERROR(Patiently(std::chrono::seconds(5), give_up,
                                  [&](grpc::ClientContext* context) { return world_->Run(context, request, &run); }));
  return run;
}

absl::StatusOr<v1::WorldRunReply> WorldBus::End(int64_t align_slots) {
  v1::EndRunRequest end;
  end.set_align_slots(align_slots);
  end.set_requested_by(caller_);
  grpc::ClientContext context;
  SetDeadline(&context, std::chrono::seconds(5));
  v1::WorldRunReply run;
  STAGE_RETURN_IF_ERROR(FromGrpcStatus(world_->EndRun(&context, end, &run)));
  return run;
}

absl::StatusOr<v1::WorldRunReply> WorldBus::Get() {
  v1::GetRunRequest get;
  get.set_requested_by(caller_);
  grpc::ClientContext context;
  SetDeadline(&context, std::chrono::seconds(1));
  v1::WorldRunReply run;
  STAGE_RETURN_IF_ERROR(FromGrpcStatus(world_->GetRun(&context, get, &run)));
  return run;
}

}  // namespace stage::sim
