// Command-line handling shared by every program (CLI11): the common flags and one-line errors with a non-zero exit.
// Include only from main.cc files: CLI11 is a large header.
#pragma once

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/common/metrics.h"

namespace grpc {
class Service;
}  // namespace grpc

namespace stage {
namespace metrics {
class MetricsServer;
}  // namespace metrics

// Flags every FaStage program takes.
struct CommonFlags {
  // Rig file (YAML or JSON), or "builtin:fastage" for the shipped default rig.
  std::string config = "builtin:fastage";
  // Where to serve gRPC ("host:port"; port 0 picks a free one).
  std::string listen;
  // spdlog level spec, e.g. "debug" or "info,controller.health=debug"; overrides SPDLOG_LEVEL.
  std::string log_level;
  // After binding, write the bound "host:port" to this file (for supervisors such as stage-sim).
  std::string port_file;
  // Where to serve Prometheus metrics over HTTP ("host:port"; port 0 picks a free one); empty: no metrics endpoint.
  std::string metrics_listen;
  // After binding the metrics endpoint, write its "host:port" to this file (needs metrics_listen).
  std::string metrics_port_file;
  // ptp4l's management socket for the PTP state this node reports; "" = /var/run/ptp4l if it exists; "none" = off.
  std::string ptp_uds;
};

// Adds --config, --log-level and --version (and --listen, --port-file, --metrics-listen, --metrics-port-file and
// --ptp-uds when `serves`) to `app`.
void AddCommonFlags(CLI::App& app, CommonFlags* flags, bool serves);

// For programs that run OpenMP loops (libtorch's, Open3D's: libgomp): its waiting threads spin unless
// OMP_WAIT_POLICY says PASSIVE, and on a machine whose cores are busy a spinning thread takes the core from the one
// it waits for (a U-Net's training step measured 2.8x slower). libgomp reads the variable when it loads, before
// main(): a program that finds it unset sets it and executes itself again (the same process id, arguments and
// descriptors). Call first thing in main(); an explicit OMP_WAIT_POLICY is kept. If the exec fails it says so on
// stderr and goes on.
void ExecWithPassiveOpenMp(char** argv);

// Parses argv. Returns nullopt to go on, or the exit code to return now: 0 after --help/--version (printed to
// stdout), 2 after a usage error (one line on stderr: "<program>: error: <what>; see --help").
std::optional<int> ParseCommandLine(CLI::App& app, int argc, char** argv);

// Prints "<program>: error: <message>" as one line on stderr and returns the exit code for it: 2 for bad input
// (InvalidArgument, NotFound, FailedPrecondition), 1 otherwise.
int ReportFatal(absl::string_view program, const absl::Status& status);

// Serves `services` and the NodeClock service (on CLOCK_REALTIME, with the PTP state of flags.ptp_uds) on
// flags.listen (or `default_listen` when the flag is empty) until SIGINT or SIGTERM, writing
// flags.port_file once serving, with the metrics endpoint flags.metrics_listen asks for (StartMetrics); then shuts down
// gracefully. Once serving it logs "serving on ADDRESS: <summary>" (the effective configuration in a line). Returns the
// process exit code. Call BlockShutdownSignals() first thing in main().
int ServeUntilSignal(absl::string_view program, const CommonFlags& flags, const std::string& default_listen,
                     const std::vector<grpc::Service*>& services, const std::string& summary);

// The process's metrics endpoint (metrics::Registry::Default() over HTTP, with the process collector), kept for as
// long as the process serves.
struct MetricsEndpoint {
  MetricsEndpoint();
  MetricsEndpoint(MetricsEndpoint&&) noexcept;
  MetricsEndpoint& operator=(MetricsEndpoint&&) noexcept;
  ~MetricsEndpoint();
  // "host:port" of the endpoint; "" when there is none.
  std::string address() const;
  metrics::Registration process;
  std::unique_ptr<metrics::MetricsServer> server;  // null when flags.metrics_listen is empty
};

// Starts the metrics endpoint flags.metrics_listen asks for (nothing when it is empty) and writes
// flags.metrics_port_file. ServeUntilSignal calls it; programs that serve otherwise (stage-sim) call it themselves.
absl::StatusOr<MetricsEndpoint> StartMetrics(absl::string_view program, const CommonFlags& flags);

// A range of virtual frames from the command line: "A:B" is [A, B), "A:" from A to the end (last = -1), "A" the one
// frame A. InvalidArgument names the flag.
absl::Status ParseFrameRange(absl::string_view flag, absl::string_view text, int64_t* first, int64_t* last);

// "1 camera node", "3 camera nodes": a count and a noun (regular English plural) for messages.
std::string Plural(int64_t n, absl::string_view noun);

// A progress bar on stderr for long work: redrawn in place on a terminal, a line every few seconds otherwise (logs,
// pipes); messages print on their own line.
class ProgressLine {
 public:
  explicit ProgressLine(std::string unit);
  void Update(int64_t done, int64_t total, const std::string& detail = "");
  void Message(const std::string& text);
  // Ends the bar's line.
  void Finish();

 private:
  std::string unit_;
  bool tty_;
  bool open_ = false;
  std::chrono::steady_clock::time_point start_, last_;
};

}  // namespace stage
