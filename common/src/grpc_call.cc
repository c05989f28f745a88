// Deadlines and patient retries of client calls: see grpc_call.h.
#include "stage/common/grpc_call.h"

#include "stage/common/grpc_status.h"

namespace stage {

void SetDeadline(grpc::ClientContext* context, std::chrono::milliseconds timeout) {
  context->set_deadline(std::chrono::system_clock::now() + timeout);
}

absl::Status Patiently(std::chrono::milliseconds per_try, std::chrono::steady_clock::time_point give_up,
                       const std::function<grpc::Status(grpc::ClientContext*)>& rpc) {
  while (true) {
    grpc::ClientContext context;
    SetDeadline(&context, per_try);
    grpc::Status s = rpc(&context);
    if (s.error_code() != grpc::StatusCode::DEADLINE_EXCEEDED || std::chrono::steady_clock::now() >= give_up) {
      return FromGrpcStatus(s);
    }
  }
}

}  // namespace stage
