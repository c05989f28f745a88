// Serves a metrics registry over HTTP for Prometheus: GET /metrics answers the text exposition format. A small pool
// (scrapes are rare and quick); the HTTP library stays inside metrics_server.cc.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/common/metrics.h"

namespace stage::metrics {

struct MetricsServerOptions {
  // "host:port" to listen on; port 0 lets the kernel choose. Loopback by default: a stage's hosts name their own
  // address (the one their Prometheus reaches) explicitly.
  std::string listen = "127.0.0.1:0";
  // Requests served at once (threads of the server's pool), 1..64.
  int threads = 2;

  absl::Status Validate() const;
};

class MetricsServer {
 public:
  // Binds and starts serving `registry` (not owned; it must outlive the server). Unavailable names the address when
  // it cannot be bound.
  static absl::StatusOr<std::unique_ptr<MetricsServer>> Start(const MetricsServerOptions& options,
                                                              const Registry* registry);
  // Stops serving and joins the server's threads.
  ~MetricsServer();

  int port() const;
  // "host:port" with the bound port.
  const std::string& address() const;

 private:
  struct Impl;
  explicit MetricsServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stage::metrics
