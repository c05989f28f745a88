// gRPC server metrics (rpc_metrics.h).
#include "rpc_metrics.h"

#include <chrono>
#include <mutex>
#include <string>
#include <unordered_map>

namespace stage {
namespace {

using grpc::experimental::InterceptionHookPoints;
using grpc::experimental::ServerRpcInfo;

// The buckets of grpc_server_handling_seconds: 100 us (a loopback call) to a minute (a take's stream).
const std::vector<double>& HandlingBounds() {
  static const std::vector<double> bounds = {0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05,
                                             0.1,    0.25,    0.5,    1,     2.5,    5,     10,   30,    60};
  return bounds;
}

const char* TypeName(ServerRpcInfo::Type type) {
  switch (type) {
    case ServerRpcInfo::Type::UNARY:
      return "unary";
    case ServerRpcInfo::Type::CLIENT_STREAMING:
      return "client_stream";
    case ServerRpcInfo::Type::SERVER_STREAMING:
      return "server_stream";
    case ServerRpcInfo::Type::BIDI_STREAMING:
      return "bidi_stream";
  }
  return "unknown";
}

// grpc-go's names of the status codes, as go-grpc-prometheus labels them.
const char* CodeName(grpc::StatusCode code) {
  static const char* const kNames[] = {
      "OK",       "Canceled",       "Unknown",          "InvalidArgument",   "DeadlineExceeded",
      "NotFound", "AlreadyExists",  "PermissionDenied", "ResourceExhausted", "FailedPrecondition",
      "Aborted",  "OutOfRange",     "Unimplemented",    "Internal",          "Unavailable",
      "DataLoss", "Unauthenticated"};
  const int i = static_cast<int>(code);
  return i >= 0 && i < static_cast<int>(std::size(kNames)) ? kNames[i] : "Unknown";
}

// The series of one method.
struct MethodMetrics {
  metrics::Counter* started = nullptr;
  metrics::Histogram* seconds = nullptr;
  metrics::Labels labels;
  std::mutex mutex;
  std::unordered_map<int, metrics::Counter*> handled;  // by status code; guarded by mutex
};

class Factory;

class MetricsInterceptor final : public grpc::experimental::Interceptor {
 public:
  MetricsInterceptor(metrics::Registry* registry, MethodMetrics* method)
      : registry_(registry), method_(method), start_(std::chrono::steady_clock::now()) {
    method_->started->Increment();
  }

  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(InterceptionHookPoints::PRE_SEND_STATUS)) {
      const grpc::Status status = methods->GetSendStatus();
      method_->seconds->Observe(std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count());
      Handled(status.error_code())->Increment();
    }
    methods->Proceed();
  }

 private:
  metrics::Counter* Handled(grpc::StatusCode code) {
    std::lock_guard<std::mutex> lock(method_->mutex);
    metrics::Counter*& counter = method_->handled[static_cast<int>(code)];
    if (counter == nullptr) {
      metrics::Labels labels = method_->labels;
      labels.emplace_back("grpc_code", CodeName(code));
      counter = registry_->GetCounter("grpc_server_handled_total",
                                      "Total number of RPCs completed on the server, regardless of success or failure.",
                                      labels);
    }
    return counter;
  }

  metrics::Registry* registry_;
  MethodMetrics* method_;
  std::chrono::steady_clock::time_point start_;
};

class Factory final : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit Factory(metrics::Registry* registry) : registry_(registry) {}

  grpc::experimental::Interceptor* CreateServerInterceptor(ServerRpcInfo* info) override {
    return new MetricsInterceptor(registry_, Method(info->method(), info->type()));
  }

 private:
  MethodMetrics* Method(const char* full_name, ServerRpcInfo::Type type) {
    const std::string key = full_name == nullptr ? "" : full_name;
    std::lock_guard<std::mutex> lock(mutex_);
    std::unique_ptr<MethodMetrics>& m = methods_[key];
    if (m == nullptr) {
      // "/package.Service/Method"
      const size_t slash = key.rfind('/');
      std::string service = slash == std::string::npos || slash == 0 ? "unknown" : key.substr(1, slash - 1);
      std::string method = slash == std::string::npos ? key : key.substr(slash + 1);
      m = std::make_unique<MethodMetrics>();
      m->labels = {{"grpc_type", TypeName(type)}, {"grpc_service", service}, {"grpc_method", method}};
      m->started =
          registry_->GetCounter("grpc_server_started_total", "Total number of RPCs started on the server.", m->labels);
      m->seconds = registry_->GetHistogram(
          "grpc_server_handling_seconds",
          "Histogram of response latency (seconds) of gRPC that had been application-level handled by the server.",
          HandlingBounds(), m->labels);
    }
    return m.get();
  }

  metrics::Registry* registry_;
  std::mutex mutex_;
  std::unordered_map<std::string, std::unique_ptr<MethodMetrics>> methods_;  // guarded by mutex_
};

}  // namespace

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> NewRpcMetricsInterceptorFactory(
    metrics::Registry* registry) {
  return std::make_unique<Factory>(registry);
}

}  // namespace stage
