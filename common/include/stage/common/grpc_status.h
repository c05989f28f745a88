// The one place where absl::Status and grpc::Status are converted (the service edge).
#pragma once

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace stage {

// Same code (the two enums share their numbering), same message.
grpc::Status ToGrpcStatus(const absl::Status& status);
absl::Status FromGrpcStatus(const grpc::Status& status);

}  // namespace stage
