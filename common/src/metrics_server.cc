// The metrics endpoint, on cpp-httplib (docs/dependencies.md).
#include "stage/common/metrics_server.h"

#include <httplib.h>

#include <atomic>
#include <chrono>
#include <thread>

#include "absl/strings/str_cat.h"
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
  std::thread thread;
  std::atomic<bool> ended{false};
  int port = 0;
  std::string address;
};

absl::StatusOr<std::unique_ptr<MetricsServer>> MetricsServer::Start(const MetricsServerOptions& options,
                                                                    const Registry* registry) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  std::string host;
  int port = 0;
  STAGE_RETURN_IF_ERROR(ParseHostPort(options.listen, &host, &port));
  auto impl = std::make_unique<Impl>();
  const int threads = options.threads;
  impl->http.new_task_queue = [threads] { return new httplib::ThreadPool(static_cast<size_t>(threads)); };
  // SO_REUSEADDR only: the library's default adds SO_REUSEPORT, which would let a second process share the port
  // instead of failing to bind it.
  impl->http.set_socket_options([](socket_t sock) {
    int yes = 1;
    setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
  });
  impl->http.set_read_timeout(5, 0);
  impl->http.set_write_timeout(5, 0);
  impl->http.Get("/metrics", [registry](const httplib::Request&, httplib::Response& response) {
    response.set_content(registry->Render(), kContentType);
  });
  impl->http.Get("/", [](const httplib::Request&, httplib::Response& response) {
    response.set_content("FaStage metrics: GET /metrics (Prometheus text format 0.0.4)\n", "text/plain");
  });
  const int bound = port == 0 ? impl->http.bind_to_any_port(host) : (impl->http.bind_to_port(host, port) ? port : -1);
  if (bound <= 0) {
    return absl::UnavailableError(absl::StrCat("metrics: cannot listen on ", options.listen,
                                               " (address in use, or not an address of this host)"));
  }
  impl->port = bound;
  impl->address = DialAddress(host, bound);
  Impl* raw = impl.get();
  impl->thread = std::thread([raw] {
    raw->http.listen_after_bind();
    raw->ended = true;
  });
  // stop() only reaches a server that runs: wait for the loop to start (or to have failed) before handing it out.
  while (!raw->http.is_running() && !raw->ended) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  if (raw->ended) {
    raw->thread.join();
    return absl::UnavailableError(absl::StrCat("metrics: the HTTP server on ", raw->address, " did not start"));
  }
  return std::unique_ptr<MetricsServer>(new MetricsServer(std::move(impl)));
}

MetricsServer::MetricsServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

MetricsServer::~MetricsServer() {
  impl_->http.stop();
  if (impl_->thread.joinable()) impl_->thread.join();
}

int MetricsServer::port() const { return impl_->port; }

const std::string& MetricsServer::address() const { return impl_->address; }

}  // namespace stage::metrics
