// Every gRPC call a FaStage server handles, counted and timed into a metrics registry by a server interceptor, under
// the names of go-grpc-prometheus that Prometheus users know: grpc_server_started_total,
// grpc_server_handled_total{grpc_code} and the grpc_server_handling_seconds histogram, labelled with the call's
// type, service and method.
#pragma once

#include <grpcpp/support/server_interceptor.h>

#include <memory>

#include "stage/common/metrics.h"

namespace stage {

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> NewRpcMetricsInterceptorFactory(
    metrics::Registry* registry);

}  // namespace stage
