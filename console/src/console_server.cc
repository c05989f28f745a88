#include "console_server.h"

#include <httplib.h>

#include <atomic>
#include <chrono>
#include <nlohmann/json.hpp>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "stage/common/clock.h"
#include "stage/common/http_server_thread.h"
#include "stage/common/logging.h"
#include "stage/common/metrics.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"

// The pages, embedded at build time (console/CMakeLists.txt).
extern const unsigned char kConsoleIndexHtml[], kConsoleIndexHtml_end[];
extern const unsigned char kConsoleAppJs[], kConsoleAppJs_end[];
extern const unsigned char kConsoleStyleCss[], kConsoleStyleCss_end[];

namespace stage::console {
namespace {

constexpr absl::string_view kCookie = "fastage_session";

std::string Bytes(const unsigned char* begin, const unsigned char* end) {
  return std::string(reinterpret_cast<const char*>(begin), static_cast<size_t>(end - begin));
}

int HttpCode(const absl::Status& s) {
  switch (s.code()) {
    case absl::StatusCode::kInvalidArgument:
    case absl::StatusCode::kOutOfRange:
      return 400;
    case absl::StatusCode::kUnauthenticated:
      return 401;
    case absl::StatusCode::kPermissionDenied:
      return 403;
    case absl::StatusCode::kNotFound:
      return 404;
    case absl::StatusCode::kFailedPrecondition:
    case absl::StatusCode::kAlreadyExists:
    case absl::StatusCode::kAborted:
      return 409;
    case absl::StatusCode::kUnavailable:
      return 503;
    case absl::StatusCode::kDeadlineExceeded:
      return 504;
    default:
      return 500;
  }
}

void SendError(httplib::Response& res, const absl::Status& s) {
  res.status = HttpCode(s);
  res.set_content(
      nlohmann::json{{"error", std::string(s.message())}, {"code", absl::StatusCodeToString(s.code())}}.dump(),
      "application/json");
}

std::string CookieToken(const httplib::Request& req) {
  for (absl::string_view part : absl::StrSplit(req.get_header_value("Cookie"), ';')) {
    part = absl::StripAsciiWhitespace(part);
    if (absl::ConsumePrefix(&part, kCookie) && absl::ConsumePrefix(&part, "=")) return std::string(part);
  }
  return "";
}

}  // namespace

absl::Status ConsoleServerOptions::Validate() const {
  std::string host;
  int port = 0;
  STAGE_RETURN_IF_ERROR(Annotate(ParseHostPort(listen, &host, &port), "--listen"));
  if (max_streams < 1 || max_streams > 256) return absl::InvalidArgumentError("--max-streams must be 1..256");
  if (request_threads < 1 || request_threads > 64) return absl::InvalidArgumentError("request threads must be 1..64");
  if (session_lifetime_s < 60)
    return absl::InvalidArgumentError("--session-hours: a login must last at least a minute");
  if (keepalive_ms < 100) return absl::InvalidArgumentError("keepalive must be at least 100 ms");
  return absl::OkStatus();
}

struct ConsoleServer::Impl {
  Impl(const ConsoleServerOptions& o, ConsoleParts p)
      : options(o), parts(p), sessions(std::chrono::seconds(o.session_lifetime_s)) {}

  ConsoleServerOptions options;
  ConsoleParts parts;
  Sessions sessions;
  httplib::Server http;
  std::atomic<bool> closing{false};
  std::atomic<int> streams{0};
  std::string url;
  metrics::Registration collector;            // before `serving`: removed after the server has stopped
  std::unique_ptr<HttpServerThread> serving;  // stopped (the destructor) before the rest goes

  using Handler = std::function<absl::StatusOr<Reply>(const httplib::Request&, const Sessions::Session&)>;

  // A route that needs a login (and, for `role` operator, an operator's). Commands (POST) also need the header
  // X-FaStage: 1, which a page of another origin cannot send without the console's consent (CORS): with the SameSite
  // cookie, no other site can drive the stage through a logged-in browser.
  void Route(bool post, const std::string& path, Role role, Handler handler) {
    auto wrapped = [this, post, role, handler, path](const httplib::Request& req, httplib::Response& res) {
      // Commands are counted by path and outcome: ok, forbidden (the role or the header), failed (the stage said no).
      auto count = [&](const char* outcome) {
        if (!post) return;
        metrics::Registry::Default()
            .GetCounter("stage_console_commands_total", "Commands the console's users gave, by path and outcome",
                        {{"path", path}, {"outcome", outcome}})
            ->Increment();
      };
      auto session = sessions.Find(CookieToken(req));
      if (!session) return SendError(res, absl::UnauthenticatedError("log in first"));
      if (post && req.get_header_value("X-FaStage") != "1") {
        count("forbidden");
        return SendError(res, absl::PermissionDeniedError("a command needs the header X-FaStage: 1"));
      }
      if (role == Role::kOperator && session->role != Role::kOperator) {
        count("forbidden");
        return SendError(res, absl::PermissionDeniedError(
                                  absl::StrCat(session->user, " is an observer: ", path, " needs an operator")));
      }
      auto reply = handler(req, *session);
      if (post) {
        Logger("console")->info("{} ({}) {}: {}", session->user, RoleName(session->role), path,
                                reply.ok() ? "ok" : std::string(reply.status().message()));
        count(reply.ok() ? "ok" : "failed");
      }
      if (!reply.ok()) return SendError(res, reply.status());
      res.set_content(reply->body, reply->content_type);
    };
    if (post) {
      http.Post(path, wrapped);
    } else {
      http.Get(path, wrapped);
    }
  }

  void Pages();
  void Login();
  void Commands();
  void Reads();
  void Stream();
};

void ConsoleServer::Impl::Pages() {
  auto page = [this](const std::string& path, const unsigned char* begin, const unsigned char* end,
                     const std::string& type) {
    std::string bytes = Bytes(begin, end);
    http.Get(path, [bytes, type](const httplib::Request&, httplib::Response& res) {
      res.set_header("Cache-Control", "no-cache");
      res.set_header("Content-Security-Policy",
                     "default-src 'self'; img-src 'self' data: blob:; style-src 'self'; connect-src 'self'");
      res.set_content(bytes, type);
    });
  };
  page("/", kConsoleIndexHtml, kConsoleIndexHtml_end, "text/html; charset=utf-8");
  page("/app.js", kConsoleAppJs, kConsoleAppJs_end, "text/javascript; charset=utf-8");
  page("/style.css", kConsoleStyleCss, kConsoleStyleCss_end, "text/css; charset=utf-8");
}

void ConsoleServer::Impl::Login() {
  http.Post("/api/login", [this](const httplib::Request& req, httplib::Response& res) {
    auto body = nlohmann::json::parse(req.body, nullptr, false);
    if (body.is_discarded() || !body.is_object() || !body.contains("user") || !body.contains("password") ||
        !body["user"].is_string() || !body["password"].is_string()) {
      return SendError(res, absl::InvalidArgumentError("login: expected {\"user\": ..., \"password\": ...}"));
    }
    const std::string user = body["user"];
    auto role = parts.users->Verify(user, body["password"].get<std::string>());
    metrics::Registry::Default()
        .GetCounter("stage_console_logins_total", "Logins to the console, by outcome",
                    {{"outcome", role.ok() ? "ok" : "refused"}})
        ->Increment();
    if (!role.ok()) {
      Logger("console")->warn("login refused for '{}' from {}", user, req.remote_addr);
      return SendError(res, role.status());
    }
    const std::string token = sessions.Open(user, *role);
    Logger("console")->info("{} logged in as {} from {}", user, RoleName(*role), req.remote_addr);
    res.set_header(
        "Set-Cookie",
        absl::StrCat(kCookie, "=", token, "; Path=/; HttpOnly; SameSite=Strict; Max-Age=", options.session_lifetime_s));
    res.set_content(nlohmann::json{{"user", user}, {"role", std::string(RoleName(*role))}}.dump(), "application/json");
  });
  http.Post("/api/logout", [this](const httplib::Request& req, httplib::Response& res) {
    sessions.Close(CookieToken(req));
    res.set_header("Set-Cookie", absl::StrCat(kCookie, "=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0"));
    res.set_content("{}", "application/json");
  });
  Route(false, "/api/me", Role::kObserver, [](const httplib::Request&, const Sessions::Session& s) {
    return Reply{"application/json", nlohmann::json{{"user", s.user}, {"role", std::string(RoleName(s.role))}}.dump()};
  });
}

void ConsoleServer::Impl::Commands() {
  StageLink* link = parts.link;
  Route(true, "/api/arm", Role::kOperator,
        [link](const httplib::Request& req, const Sessions::Session&) { return link->Arm(req.body); });
  Route(true, "/api/capture", Role::kOperator,
        [link](const httplib::Request& req, const Sessions::Session&) { return link->Capture(req.body); });
  Route(true, "/api/pause", Role::kOperator,
        [link](const httplib::Request&, const Sessions::Session&) { return link->Pause(); });
  Route(true, "/api/resume", Role::kOperator,
        [link](const httplib::Request&, const Sessions::Session&) { return link->Resume(); });
  Route(true, "/api/abort", Role::kOperator,
        [link](const httplib::Request&, const Sessions::Session&) { return link->Abort(); });
  // Anyone logged in may stop the lights; only an operator may let them on again.
  Route(true, "/api/estop", Role::kObserver, [link](const httplib::Request&, const Sessions::Session& s) {
    return link->EmergencyStop(absl::StrCat("console: ", s.user));
  });
  Route(true, "/api/estop/reset", Role::kOperator,
        [link](const httplib::Request&, const Sessions::Session&) { return link->ResetEmergencyStop(); });
  AlarmBook* alarms = parts.alarms;
  EventLog* events = parts.events;
  Route(true, "/api/alarms/ack", Role::kOperator,
        [alarms, events](const httplib::Request& req, const Sessions::Session& s) -> absl::StatusOr<Reply> {
          auto body = nlohmann::json::parse(req.body, nullptr, false);
          if (body.is_discarded() || !body.contains("id") || !body["id"].is_number_integer()) {
            return absl::InvalidArgumentError("expected {\"id\": ALARM}");
          }
          auto alarm = alarms->Acknowledge(body["id"].get<int64_t>(), s.user, UnixNowNs());
          if (!alarm.ok()) return alarm.status();
          events->Publish("alarm", alarm->ToJson());
          return Reply{"application/json", alarm->ToJson()};
        });
}

void ConsoleServer::Impl::Reads() {
  StageLink* link = parts.link;
  Route(false, "/api/status", Role::kObserver, [link](const httplib::Request&, const Sessions::Session&) {
    return Reply{"application/json", link->LatestStatusJson()};
  });
  Route(false, "/api/preview", Role::kObserver, [link](const httplib::Request& req, const Sessions::Session&) {
    return link->Preview(req.get_param_value("camera"));
  });
  Route(false, "/api/takes", Role::kObserver,
        [link](const httplib::Request&, const Sessions::Session&) { return link->Takes(); });
  Route(false, "/api/take", Role::kObserver, [link](const httplib::Request& req, const Sessions::Session&) {
    return link->Take(req.has_param("id") ? req.get_param_value("id") : "latest");
  });
  Route(false, "/api/ledger", Role::kObserver,
        [link](const httplib::Request& req, const Sessions::Session&) -> absl::StatusOr<Reply> {
          int page_size = 1000;
          if (req.has_param("page_size") && !absl::SimpleAtoi(req.get_param_value("page_size"), &page_size)) {
            return absl::InvalidArgumentError("page_size: not a number");
          }
          return link->Ledger(req.has_param("take") ? req.get_param_value("take") : "latest",
                              req.get_param_value("lost_only") == "true", page_size, req.get_param_value("page_token"));
        });
  Route(false, "/api/timing", Role::kObserver,
        [link](const httplib::Request&, const Sessions::Session&) { return link->Timing(); });
  Route(false, "/api/timing.svg", Role::kObserver,
        [link](const httplib::Request&, const Sessions::Session&) { return link->TimingSvg(); });
  AlarmBook* alarms = parts.alarms;
  Route(false, "/api/alarms", Role::kObserver,
        [alarms](const httplib::Request&, const Sessions::Session&) -> absl::StatusOr<Reply> {
          auto history = alarms->History(200);
          if (!history.ok()) return history.status();
          // Each alarm is JSON already: joined, not parsed again.
          auto json = [](const std::vector<Alarm>& list) {
            return absl::StrCat(
                "[", absl::StrJoin(list, ",", [](std::string* out, const Alarm& a) { out->append(a.ToJson()); }), "]");
          };
          return Reply{"application/json",
                       absl::StrCat(R"({"active":)", json(alarms->Active()), R"(,"history":)", json(*history), "}")};
        });
  LogTail* logs = parts.logs;
  Route(false, "/api/log", Role::kObserver, [logs](const httplib::Request&, const Sessions::Session&) {
    return Reply{"application/json", logs->RecentJson()};
  });
}

void ConsoleServer::Impl::Stream() {
  http.Get("/api/events", [this](const httplib::Request& req, httplib::Response& res) {
    if (!sessions.Find(CookieToken(req))) return SendError(res, absl::UnauthenticatedError("log in first"));
    if (streams.fetch_add(1) >= options.max_streams) {
      streams.fetch_sub(1);
      return SendError(res, absl::UnavailableError(absl::StrCat("the console serves at most ", options.max_streams,
                                                                " event streams; close another page")));
    }
    struct State {
      uint64_t after = 0;
      bool first = true;
    };
    auto state = std::make_shared<State>();
    const std::string last =
        req.has_header("Last-Event-ID") ? req.get_header_value("Last-Event-ID") : req.get_param_value("last_event_id");
    const bool resuming = !last.empty() && absl::SimpleAtoi(last, &state->after);
    if (!resuming) state->after = parts.events->last_id();
    res.set_header("Cache-Control", "no-cache");
    res.set_header("X-Accel-Buffering", "no");
    res.set_chunked_content_provider(
        "text/event-stream",
        [this, state, resuming](size_t, httplib::DataSink& sink) {
          if (closing) return false;
          std::string out;
          if (state->first) {
            state->first = false;
            out = "retry: 1000\n\n";
            // A new follower starts from the state as it is now (the events after it follow).
            if (!resuming) {
              out += FormatServerSentEvent({state->after, "status", parts.link->LatestStatusJson()});
              if (!sink.write(out.data(), out.size())) return false;
              return true;
            }
          }
          bool gap = false;
          const auto events = parts.events->After(state->after, std::chrono::milliseconds(options.keepalive_ms), &gap);
          if (closing) return false;
          if (gap) out += FormatServerSentEvent({0, "resync", "{}"});
          if (events.empty()) out += ": keep-alive\n\n";
          for (const ConsoleEvent& e : events) {
            out += FormatServerSentEvent(e);
            state->after = e.id;
          }
          return sink.write(out.data(), out.size());
        },
        [this](bool) { streams.fetch_sub(1); });
  });
}

absl::StatusOr<std::unique_ptr<ConsoleServer>> ConsoleServer::Start(const ConsoleServerOptions& options,
                                                                    ConsoleParts parts) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  auto impl = std::make_unique<Impl>(options, parts);
  const size_t threads = static_cast<size_t>(options.max_streams + options.request_threads);
  impl->http.new_task_queue = [threads] { return new httplib::ThreadPool(threads); };
  impl->http.set_read_timeout(10, 0);
  impl->http.set_write_timeout(10, 0);
  impl->Pages();
  impl->Login();
  impl->Commands();
  impl->Reads();
  impl->Stream();
  Impl* raw = impl.get();
  impl->collector = metrics::Registry::Default().AddCollector([raw](metrics::Writer& w) {
    w.Gauge("stage_console_event_streams", "Event streams (open pages) the console serves now", {},
            raw->streams.load());
    w.Gauge("stage_console_controller_up", "1 while the console follows the controller, else 0", {},
            raw->parts.link->connected() ? 1 : 0);
  });
  STAGE_ASSIGN_OR_RETURN(impl->serving, HttpServerThread::Start(&impl->http, options.listen, "console"));
  impl->url = absl::StrCat("http://", impl->serving->address(), "/");
  return std::unique_ptr<ConsoleServer>(new ConsoleServer(std::move(impl)));
}

ConsoleServer::ConsoleServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

ConsoleServer::~ConsoleServer() {
  impl_->closing = true;
  impl_->parts.events->Close();
  impl_->serving.reset();
}

const std::string& ConsoleServer::url() const { return impl_->url; }
int ConsoleServer::port() const { return impl_->serving->port(); }
const std::string& ConsoleServer::address() const { return impl_->serving->address(); }

}  // namespace stage::console
