// Command-line handling shared by every program.
#include "stage/common/cli.h"

#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <iostream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "stage/common/logging.h"
#include "stage/common/metrics_server.h"
#include "stage/common/node_clock.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/common/shutdown.h"
#include "stage/common/status.h"
#include "stage/common/version.h"

namespace stage {

void ExecWithPassiveOpenMp(char** argv) {
  if (std::getenv("OMP_WAIT_POLICY") != nullptr) return;
  setenv("OMP_WAIT_POLICY", "PASSIVE", 1);
  execv("/proc/self/exe", argv);
  std::cerr << argv[0] << ": warning: could not execute itself again with OMP_WAIT_POLICY=PASSIVE ("
            << std::strerror(errno) << "); OpenMP's threads will spin while they wait\n";
}

void AddCommonFlags(CLI::App& app, CommonFlags* flags, bool serves) {
  app.set_version_flag("--version", std::string(app.get_name()) + " (FaStage) " + std::string(kVersion));
  app.add_option("--config", flags->config, "Rig file (YAML or JSON), or builtin:fastage for the shipped FaStage rig")
      ->capture_default_str();
  app.add_option("--log-level", flags->log_level,
                 "Log levels, e.g. debug or info,controller.health=debug (overrides SPDLOG_LEVEL)");
  if (serves) {
    app.add_option("--listen", flags->listen, "Address to serve gRPC on, host:port (port 0 picks a free port)");
    app.add_option("--port-file", flags->port_file,
                   "Write the bound host:port to this file once serving (used by stage-sim)");
    app.add_option("--metrics-listen", flags->metrics_listen,
                   "Serve Prometheus metrics over HTTP at http://HOST:PORT/metrics (port 0 picks a free port); off "
                   "when not given");
    app.add_option("--metrics-port-file", flags->metrics_port_file,
                   "Write the metrics endpoint's bound host:port to this file once serving (used by stage-sim)");
    app.add_option("--ptp-uds", flags->ptp_uds,
                   "ptp4l management socket whose PTP state this node reports (default: /var/run/ptp4l if it "
                   "exists; none: off)");
  }
}

std::optional<int> ParseCommandLine(CLI::App& app, int argc, char** argv) {
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    std::cout << app.help();
    return 0;
  } catch (const CLI::CallForAllHelp& e) {
    std::cout << app.help("", CLI::AppFormatMode::All);
    return 0;
  } catch (const CLI::CallForVersion& e) {
    std::cout << e.what() << "\n";
    return 0;
  } catch (const CLI::ParseError& e) {
    std::string what = absl::StrReplaceAll(e.what(), {{"\n", "; "}});
    std::cerr << app.get_name() << ": error: " << what << "; see --help\n";
    return 2;
  }
  return std::nullopt;
}

int ReportFatal(absl::string_view program, const absl::Status& status) {
  std::string message = absl::StrReplaceAll(status.message(), {{"\n", "; "}});
  std::cerr << program << ": error: " << message << "\n";
  switch (status.code()) {
    case absl::StatusCode::kInvalidArgument:
    case absl::StatusCode::kNotFound:
    case absl::StatusCode::kFailedPrecondition:
      return 2;
    default:
      return 1;
  }
}

int ServeUntilSignal(absl::string_view program, const CommonFlags& flags, const std::string& default_listen,
                     const std::vector<grpc::Service*>& services, const std::string& summary) {
  RpcServerOptions options;
  options.listen = flags.listen.empty() ? default_listen : flags.listen;
  // Every node answers NodeClock on the clock it stamps and fires with: CLOCK_REALTIME (PTP-disciplined in
  // production).
  RealClock clock(RealClock::Kind::kRealtime);
  std::unique_ptr<PtpProbe> ptp = MakePtpProbe(flags.ptp_uds);
  NodeClockService clock_service(&clock, "CLOCK_REALTIME", ptp.get());
  std::vector<grpc::Service*> all = services;
  all.push_back(&clock_service);
  auto server = RpcServer::Start(options, all);
  if (!server.ok()) return ReportFatal(program, server.status());
  auto log = Logger("rpc");
  auto metrics = StartMetrics(program, flags);
  if (!metrics.ok()) return ReportFatal(program, metrics.status());
  if (!flags.port_file.empty()) {
    if (absl::Status s = WriteAddressFile(flags.port_file, (*server)->address()); !s.ok()) {
      return ReportFatal(program, s);
    }
  }
  log->info("serving on {} ({}): {}", (*server)->address(), DescribeTransportSecurity(), summary);
  std::optional<int> sig = WaitForShutdownSignal();
  log->info("{} received; shutting down", sig && *sig == SIGINT ? "SIGINT" : "SIGTERM");
  (*server)->Shutdown();
  return 0;
}

MetricsEndpoint::MetricsEndpoint() = default;
MetricsEndpoint::MetricsEndpoint(MetricsEndpoint&&) noexcept = default;
MetricsEndpoint& MetricsEndpoint::operator=(MetricsEndpoint&&) noexcept = default;
MetricsEndpoint::~MetricsEndpoint() = default;

std::string MetricsEndpoint::address() const { return server ? server->address() : std::string(); }

absl::StatusOr<MetricsEndpoint> StartMetrics(absl::string_view program, const CommonFlags& flags) {
  MetricsEndpoint endpoint;
  if (flags.metrics_listen.empty()) {
    if (!flags.metrics_port_file.empty()) {
      return absl::InvalidArgumentError("--metrics-port-file needs --metrics-listen");
    }
    return endpoint;
  }
  metrics::Registry& registry = metrics::Registry::Default();
  endpoint.process = metrics::RegisterProcessCollector(registry, program);
  metrics::MetricsServerOptions options;
  options.listen = flags.metrics_listen;
  auto server = metrics::MetricsServer::Start(options, &registry);
  if (!server.ok()) return Annotate(server.status(), "--metrics-listen");
  endpoint.server = *std::move(server);
  if (!flags.metrics_port_file.empty()) {
    STAGE_RETURN_IF_ERROR(WriteAddressFile(flags.metrics_port_file, endpoint.server->address()));
  }
  Logger("metrics")->info("metrics on http://{}/metrics", endpoint.server->address());
  return endpoint;
}

std::string Plural(int64_t n, absl::string_view noun) { return absl::StrCat(n, " ", noun, n == 1 ? "" : "s"); }

absl::Status ParseFrameRange(absl::string_view flag, absl::string_view text, int64_t* first, int64_t* last) {
  const size_t colon = text.find(':');
  bool ok = absl::SimpleAtoi(text.substr(0, colon), first) && *first >= 0;
  if (colon == absl::string_view::npos) {
    *last = *first + 1;
  } else if (colon + 1 == text.size()) {
    *last = -1;
  } else {
    ok = ok && absl::SimpleAtoi(text.substr(colon + 1), last) && *last > *first;
  }
  if (!ok) {
    return absl::InvalidArgumentError(
        absl::StrCat(flag, " \"", text, "\" is not a frame range: A:B (B excluded, B > A >= 0), A: or A"));
  }
  return absl::OkStatus();
}

ProgressLine::ProgressLine(std::string unit)
    : unit_(std::move(unit)),
      tty_(isatty(STDERR_FILENO) != 0),
      start_(std::chrono::steady_clock::now()),
      last_(start_ - std::chrono::hours(1)) {}

void ProgressLine::Update(int64_t done, int64_t total, const std::string& detail) {
  const auto now = std::chrono::steady_clock::now();
  if (!tty_ && done < total && now - last_ < std::chrono::seconds(3)) return;
  last_ = now;
  const double frac = total > 0 ? static_cast<double>(done) / static_cast<double>(total) : 0;
  const int bar = static_cast<int>(frac * 30);
  const double elapsed = std::chrono::duration<double>(now - start_).count();
  std::cerr << (tty_ ? "\r\033[K" : "") << "[" << std::string(static_cast<size_t>(bar), '#')
            << std::string(static_cast<size_t>(30 - bar), '.') << "] "
            << absl::StrFormat("%3.0f%% %d/%d %s, %.1f s", 100 * frac, done, total, unit_, elapsed)
            << (detail.empty() ? "" : "  ") << detail << (tty_ ? "" : "\n") << std::flush;
  open_ = tty_;
}

void ProgressLine::Message(const std::string& text) {
  if (open_) std::cerr << "\n";
  open_ = false;
  std::cerr << text << std::endl;
}

void ProgressLine::Finish() {
  if (open_) std::cerr << "\n" << std::flush;
  open_ = false;
}

}  // namespace stage
