#include "stage/common/http_server_thread.h"

#include <httplib.h>
#include <netinet/tcp.h>

#include <chrono>

#include "absl/strings/str_cat.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"

namespace stage {

absl::StatusOr<std::unique_ptr<HttpServerThread>> HttpServerThread::Start(httplib::Server* server,
                                                                          const std::string& listen,
                                                                          const std::string& what) {
  std::string host;
  int port = 0;
  STAGE_RETURN_IF_ERROR(Annotate(ParseHostPort(listen, &host, &port), absl::StrCat(what, " listen")));
  server->set_socket_options([](socket_t sock) {
    int yes = 1;
    setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
    setsockopt(sock, IPPROTO_TCP, TCP_NODELAY, &yes, sizeof(yes));
  });
  const int bound = port == 0 ? server->bind_to_any_port(host) : (server->bind_to_port(host, port) ? port : -1);
  if (bound <= 0) {
    return absl::UnavailableError(
        absl::StrCat(what, ": cannot listen on ", listen, " (address in use, or not an address of this host)"));
  }
  std::unique_ptr<HttpServerThread> t(new HttpServerThread());
  t->server_ = server;
  t->port_ = bound;
  t->address_ = DialAddress(host, bound);
  HttpServerThread* raw = t.get();
  t->thread_ = std::thread([raw] {
    raw->server_->listen_after_bind();
    raw->ended_ = true;
  });
  // stop() only reaches a server that runs: wait for the loop to start (or to have failed) before handing it out.
  while (!server->is_running() && !raw->ended_) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  if (raw->ended_) {
    raw->thread_.join();
    return absl::UnavailableError(absl::StrCat(what, ": the HTTP server on ", raw->address_, " did not start"));
  }
  return t;
}

HttpServerThread::~HttpServerThread() {
  server_->stop();
  if (thread_.joinable()) thread_.join();
}

}  // namespace stage
