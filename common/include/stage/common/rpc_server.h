// A gRPC server as every FaStage process runs it: one listen address (port 0 picks a free port, reported back),
// message size raised for frames, keepalive, the standard grpc.health.v1 service, every call counted and timed for
// the metrics, and graceful shutdown.
#pragma once

#include <atomic>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace grpc {
class Server;
class Service;
}  // namespace grpc

namespace stage {
namespace metrics {
class Registry;
}  // namespace metrics
struct TransportSecurity;

struct RpcServerOptions {
  // "host:port"; port 0 lets the kernel choose. In plain text only a loopback address (IsLoopbackHost): serving other
  // hosts needs mutual TLS.
  std::string listen = "127.0.0.1:0";
  // Largest message accepted or sent, bytes. Default 64 MiB: a full 4096x2304 16-bit frame is 18 MiB.
  int max_message_bytes = 64 << 20;
  // Keepalive ping interval and timeout for idle connections, ms.
  int keepalive_time_ms = 10000;
  int keepalive_timeout_ms = 5000;
  // Time in-flight calls get to finish on Shutdown() before they are cancelled, ms.
  int shutdown_grace_ms = 2000;
  // Where every call is counted and timed (grpc_server_* families, rpc_metrics.h); nullptr: the process's registry.
  metrics::Registry* metrics = nullptr;
  // How the server's transport is secured (rpc_channel.h); nullptr: the process's (SetTransportSecurity).
  const TransportSecurity* security = nullptr;

  absl::Status Validate() const;
};

class RpcServer {
 public:
  // Builds and starts the server with `services` (not owned; they must outlive the server). Fails with a message
  // naming the address if it cannot be bound.
  static absl::StatusOr<std::unique_ptr<RpcServer>> Start(const RpcServerOptions& options,
                                                          const std::vector<grpc::Service*>& services);
  ~RpcServer();

  // The port actually bound (the chosen one when listen asked for port 0).
  int port() const { return port_; }
  // "host:port" with the bound port, for clients.
  const std::string& address() const { return address_; }

  // Marks the health service SERVING or NOT_SERVING.
  void SetServing(bool serving);

  // Reports NOT_SERVING, stops accepting calls, gives in-flight calls the grace period, then cancels them.
  // Idempotent; the destructor calls it.
  void Shutdown();

  // Blocks until Shutdown() has completed (from another thread).
  void Wait();

 private:
  RpcServer(std::unique_ptr<grpc::Server> server, int port, std::string address, int grace_ms);
  std::unique_ptr<grpc::Server> server_;
  int port_;
  std::string address_;
  int grace_ms_;
  std::atomic<bool> shut_down_{false};
};

// Whether `host` (of "host:port") is this machine's loopback: 127.0.0.0/8, ::1 or localhost.
bool IsLoopbackHost(absl::string_view host);

// Writes `address` to `path` atomically (temporary file + rename), so a reader never sees a partial address.
// Used by programs started with --port-file to tell their parent where they listen.
absl::Status WriteAddressFile(const std::string& path, const std::string& address);

}  // namespace stage
