// stage-console's HTTP side: the pages (embedded: no fetch leaves the console), a JSON API for commands and reads, one
// Server-Sent Events stream (status, take progress, alarms, log lines, with ids a reconnecting browser resumes from),
// and the login that gates them all (docs/console.md). The only source that includes cpp-httplib's header.
#pragma once

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "alarms.h"
#include "event_log.h"
#include "log_tail.h"
#include "stage_link.h"
#include "users.h"

namespace stage::console {

struct ConsoleServerOptions {
  // Where to serve HTTP, host:port (port 0 picks a free one).
  std::string listen = "127.0.0.1:8470";
  // Event streams served at once; more are refused (503): each holds one of the server's threads.
  int max_streams = 24;
  // Threads for requests that are not streams (commands, reads, pages).
  int request_threads = 8;
  // A login lasts this long after its last use, s.
  int session_lifetime_s = 12 * 3600;
  // An idle event stream gets a comment line this often, ms (proxies and browsers keep it open).
  int keepalive_ms = 15000;

  // InvalidArgument naming the field.
  absl::Status Validate() const;
};

// What the server serves from; not owned, each must outlive the server.
struct ConsoleParts {
  StageLink* link = nullptr;
  EventLog* events = nullptr;
  AlarmBook* alarms = nullptr;
  LogTail* logs = nullptr;
  const UserBook* users = nullptr;
};

class ConsoleServer {
 public:
  // Binds and starts serving on its own threads. Unavailable when the address cannot be bound.
  static absl::StatusOr<std::unique_ptr<ConsoleServer>> Start(const ConsoleServerOptions& options, ConsoleParts parts);
  // Stops serving; the event streams end.
  ~ConsoleServer();

  // "http://host:port/", and "host:port" as clients dial it.
  const std::string& url() const;
  const std::string& address() const;
  int port() const;

 private:
  struct Impl;
  explicit ConsoleServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stage::console
