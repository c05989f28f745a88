// gRPC server wrapper.
#include "stage/common/rpc_server.h"

#include <arpa/inet.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <netinet/in.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "rpc_metrics.h"
#include "stage/common/file_util.h"
#include "stage/common/metrics.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"

namespace stage {

absl::Status RpcServerOptions::Validate() const {
  std::string host;
  int port;
  STAGE_RETURN_IF_ERROR(Annotate(ParseHostPort(listen, &host, &port), "listen"));
  if (max_message_bytes < (1 << 20)) return absl::InvalidArgumentError("max_message_bytes must be >= 1 MiB");
  if (keepalive_time_ms <= 0 || keepalive_timeout_ms <= 0) {
    return absl::InvalidArgumentError("keepalive_time_ms and keepalive_timeout_ms must be > 0");
  }
  if (shutdown_grace_ms < 0) return absl::InvalidArgumentError("shutdown_grace_ms must be >= 0");
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<RpcServer>> RpcServer::Start(const RpcServerOptions& options,
                                                            const std::vector<grpc::Service*>& services) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (services.empty()) return absl::InvalidArgumentError("RpcServer needs at least one service");
  std::string host;
  int ignored;
  (void)ParseHostPort(options.listen, &host, &ignored);  // valid: Validate() parsed it
  const TransportSecurity security = options.security != nullptr ? *options.security : ProcessTransportSecurity();
  if (security.mode == TransportSecurity::Mode::kPlainText) {
    if (!IsLoopbackHost(host)) {
      return absl::FailedPreconditionError(
          absl::StrCat("will not listen on ", options.listen,
                       " in plain text: plain text is for loopback only (127.0.0.0/8, ::1); "
                       "serving other hosts needs the rig's security.transport: mutual-tls (docs/security.md)"));
    }
  }
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort(options.listen, MakeServerCredentials(security), &port);
  builder.SetMaxReceiveMessageSize(options.max_message_bytes);
  builder.SetMaxSendMessageSize(options.max_message_bytes);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIME_MS, options.keepalive_time_ms);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, options.keepalive_timeout_ms);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 1000);
  // A port in use must be an error, not a second server sharing it.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
  interceptors.push_back(
      NewRpcMetricsInterceptorFactory(options.metrics != nullptr ? options.metrics : &metrics::Registry::Default()));
  builder.experimental().SetInterceptorCreators(std::move(interceptors));
  for (grpc::Service* service : services) builder.RegisterService(service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (server == nullptr || port == 0) {
    return absl::UnavailableError(
        absl::StrCat("cannot listen on ", options.listen, " (address in use, or not an address of this host)"));
  }
  auto result = std::unique_ptr<RpcServer>(
      new RpcServer(std::move(server), port, DialAddress(host, port), options.shutdown_grace_ms));
  result->SetServing(true);
  return result;
}

RpcServer::RpcServer(std::unique_ptr<grpc::Server> server, int port, std::string address, int grace_ms)
    : server_(std::move(server)), port_(port), address_(std::move(address)), grace_ms_(grace_ms) {}

RpcServer::~RpcServer() { Shutdown(); }

void RpcServer::SetServing(bool serving) {
  if (auto* health = server_->GetHealthCheckService()) health->SetServingStatus(serving);
}

void RpcServer::Shutdown() {
  if (shut_down_.exchange(true)) return;
  SetServing(false);
  server_->Shutdown(std::chrono::system_clock::now() + std::chrono::milliseconds(grace_ms_));
  server_->Wait();
}

void RpcServer::Wait() { server_->Wait(); }

bool IsLoopbackHost(absl::string_view host) {
  if (absl::StartsWith(host, "[") && absl::EndsWith(host, "]")) host = host.substr(1, host.size() - 2);
  if (host == "localhost") return true;
  const std::string text(host);
  in_addr v4{};
  if (inet_pton(AF_INET, text.c_str(), &v4) == 1) return (ntohl(v4.s_addr) >> 24) == 127;
  in6_addr v6{};
  if (inet_pton(AF_INET6, text.c_str(), &v6) != 1) return false;  // a name: it could resolve anywhere
  if (IN6_IS_ADDR_LOOPBACK(&v6)) return true;
  return IN6_IS_ADDR_V4MAPPED(&v6) && v6.s6_addr[12] == 127;
}

absl::Status WriteAddressFile(const std::string& path, const std::string& address) {
  return WriteFileAtomically(path, address + "\n");
}

}  // namespace stage
