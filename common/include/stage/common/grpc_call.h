// Calling a node's RPC from a client: a deadline per try, and requests asked again while a node is slow to answer.
#pragma once

#include <grpcpp/client_context.h>

#include <chrono>
#include <functional>

#include "absl/status/status.h"

namespace stage {

// Sets `context`'s deadline `timeout` from now.
void SetDeadline(grpc::ClientContext* context, std::chrono::milliseconds timeout);

// Calls `rpc` with a fresh context and a deadline of `per_try` a try until the node answers, fails for another reason
// than its deadline (it is gone, or refuses), or `give_up` has passed; the last answer, as an absl::Status. For
// requests a node answers the same when asked twice (arming a take, its plan, disarming): a node slow to answer on a
// loaded host is asked again rather than counted out.
absl::Status Patiently(std::chrono::milliseconds per_try, std::chrono::steady_clock::time_point give_up,
                       const std::function<grpc::Status(grpc::ClientContext*)>& rpc);

}  // namespace stage
