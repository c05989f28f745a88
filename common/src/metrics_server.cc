// The metrics endpoint, on cpp-httplib (docs/dependencies.md).
#include "stage/common/metrics_server.h"

#include <httplib.h>

#include "absl/strings/str_cat.h"
#include "stage/common/http_server_thread.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"

namespace stage::metrics {

absl::Status MetricsServerOptions::Validate() const {
  std::string host;
  int port;
  STAGE_RETURN_IF_ERROR(Annotate(ParseHostPort(listen, &host, &port), "metrics listen"));
  if (threads < 1 || threads > 64) return absl::InvalidArgumentError("metrics server threads must be 1..64");
  return absl::OkStatus();
}

struct MetricsServer::Impl {
  httplib::Server http;
  std::unique_ptr<HttpServerThread> serving;  // last: stopped before the server goes
};

absl::StatusOr<std::unique_ptr<MetricsServer>> MetricsServer::Start(const MetricsServerOptions& options,
                                                                    const Registry* registry) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  auto impl = std::make_unique<Impl>();
  const int threads = options.threads;
  impl->http.new_task_queue = [threads] { return new httplib::ThreadPool(static_cast<size_t>(threads)); };
  impl->http.set_read_timeout(5, 0);
  impl->http.set_write_timeout(5, 0);
  impl->http.Get("/metrics", [registry](const httplib::Request&, httplib::Response& response) {
    response.set_content(registry->Render(), kContentType);
  });
  impl->http.Get("/", [](const httplib::Request&, httplib::Response& response) {
    response.set_content("FaStage metrics: GET /metrics (Prometheus text format 0.0.4)\n", "text/plain");
  });
  STAGE_ASSIGN_OR_RETURN(impl->serving, HttpServerThread::Start(&impl->http, options.listen, "metrics"));
  return std::unique_ptr<MetricsServer>(new MetricsServer(std::move(impl)));
}

MetricsServer::MetricsServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

MetricsServer::~MetricsServer() = default;

int MetricsServer::port() const { return impl_->serving->port(); }

const std::string& MetricsServer::address() const { return impl_->serving->address(); }

}  // namespace stage::metrics
