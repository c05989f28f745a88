// One cpp-httplib server bound and run on a thread of its own, as the metrics endpoint and stage-console run theirs:
// SO_REUSEADDR only (the library's default SO_REUSEPORT would let a second process share the port silently),
// TCP_NODELAY, and a start that returns once the server serves. The library's header stays out of this one.
#pragma once

#include <atomic>
#include <memory>
#include <string>
#include <thread>

#include "absl/status/statusor.h"

namespace httplib {
class Server;
}

namespace stage {

class HttpServerThread {
 public:
  // Binds `server` (routes set, not owned; it must outlive this) to `listen` ("host:port", port 0: a free one) and
  // serves on a thread. Unavailable names `what` and the address when it cannot be bound or does not start.
  static absl::StatusOr<std::unique_ptr<HttpServerThread>> Start(httplib::Server* server, const std::string& listen,
                                                                 const std::string& what);
  // Stops the server and joins its thread.
  ~HttpServerThread();

  int port() const { return port_; }
  // "host:port" with the bound port, as clients dial it (DialAddress).
  const std::string& address() const { return address_; }

 private:
  HttpServerThread() = default;

  httplib::Server* server_ = nullptr;
  std::thread thread_;
  std::atomic<bool> ended_{false};
  int port_ = 0;
  std::string address_;
};

}  // namespace stage
