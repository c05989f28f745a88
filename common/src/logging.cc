// spdlog setup with named loggers.
#include "stage/common/logging.h"

#include <grpc/support/log.h>

#include <cstdlib>
#include <mutex>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "spdlog/cfg/helpers.h"
#include "spdlog/sinks/stdout_color_sinks.h"
#include "spdlog/spdlog.h"

namespace stage {
namespace {

std::mutex g_mutex;
spdlog::sink_ptr g_sink;  // guarded by g_mutex

spdlog::sink_ptr Sink() {
  std::lock_guard<std::mutex> lock(g_mutex);
  if (!g_sink) g_sink = std::make_shared<spdlog::sinks::stderr_color_sink_mt>();
  return g_sink;
}

// gRPC's own log lines (gpr_log) go to the "grpc" logger, so they share the format and the level settings. gRPC
// reports failures to its caller too, and FaStage reports those itself: the "grpc" logger is quiet (error) unless
// a level spec names it (SPDLOG_LEVEL=grpc=debug).
void GrpcLogToSpdlog(gpr_log_func_args* args) {
  static auto logger = Logger("grpc");
  // A refused TLS handshake (a certificate of another CA, a plain-text peer) is only ever seen here: said always, in
  // words, on "rpc.tls".
  const absl::string_view message = args->message;
  if (absl::StrContains(message, "Handshake failed")) {
    static auto tls = Logger("rpc.tls");
    const char* why = absl::StrContains(message, "certificate verify failed")
                          ? "the peer's certificate is not signed by this stage's CA, or is not valid now"
                      : absl::StrContains(message, "wrong version number")
                          ? "the peer does not speak TLS (a plain-text client, or another protocol)"
                      : absl::StrContains(message, "did not return a certificate") ? "the peer presented no certificate"
                                                                                   : "see gRPC's words";
    tls->warn("refused a connection: TLS handshake failed: {} ({})", why, message);
  }
  spdlog::level::level_enum level = spdlog::level::debug;
  if (args->severity == GPR_LOG_SEVERITY_ERROR) level = spdlog::level::warn;
  if (args->severity == GPR_LOG_SEVERITY_INFO) level = spdlog::level::info;
  logger->log(level, "{} ({}:{})", args->message, args->file, args->line);
}

}  // namespace

absl::Status ValidateLogLevels(absl::string_view levels) {
  for (absl::string_view part : absl::StrSplit(levels, ',', absl::SkipEmpty())) {
    absl::string_view level = part;
    if (auto eq = part.find('='); eq != absl::string_view::npos) level = part.substr(eq + 1);
    std::string name = absl::AsciiStrToLower(level);
    if (spdlog::level::from_str(name) == spdlog::level::off && name != "off") {
      return absl::InvalidArgumentError(
          absl::StrCat("log level \"", level, "\" is not one of trace, debug, info, warn, error, critical, off"));
    }
  }
  return absl::OkStatus();
}

absl::Status InitLogging(absl::string_view program, absl::string_view levels) {
  if (absl::Status s = ValidateLogLevels(levels); !s.ok()) return s;
  auto default_logger = std::make_shared<spdlog::logger>(std::string(program), Sink());
  spdlog::set_default_logger(default_logger);
  // The registry's formatter is cloned into every logger created later, so set it there, not on the sink.
  spdlog::set_pattern(absl::StrCat("%Y-%m-%d %H:%M:%S.%e ", program, "[%P] %^%l%$ %n: %v"));
  spdlog::set_level(spdlog::level::info);
  // spdlog replaces its whole level table on each load, so the environment and the flag are loaded as one spec in
  // which the flag's entries come last and win.
  std::string spec;
  const char* env = std::getenv("SPDLOG_LEVEL");
  if (env != nullptr && ValidateLogLevels(env).ok()) spec = env;
  if (!levels.empty()) spec = spec.empty() ? std::string(levels) : absl::StrCat(spec, ",", levels);
  if (!spec.empty()) spdlog::cfg::helpers::load_levels(spec);
  if (spec.find("grpc=") == std::string::npos) Logger("grpc")->set_level(spdlog::level::err);
  // Let gRPC format only what the "grpc" logger will print.
  auto grpc_level = Logger("grpc")->level();
  gpr_set_log_verbosity(grpc_level <= spdlog::level::debug  ? GPR_LOG_SEVERITY_DEBUG
                        : grpc_level <= spdlog::level::info ? GPR_LOG_SEVERITY_INFO
                                                            : GPR_LOG_SEVERITY_ERROR);
  gpr_set_log_function(GrpcLogToSpdlog);
  if (env != nullptr && !ValidateLogLevels(env).ok()) {
    spdlog::warn("ignoring SPDLOG_LEVEL=\"{}\": not a valid level spec", env);
  }
  return absl::OkStatus();
}

std::shared_ptr<spdlog::logger> Logger(const std::string& name) {
  // spdlog's registry is thread-safe; creation is serialized so two threads never register the same name.
  static std::mutex create_mutex;
  std::lock_guard<std::mutex> lock(create_mutex);
  if (auto existing = spdlog::get(name)) return existing;
  auto logger = std::make_shared<spdlog::logger>(name, Sink());
  spdlog::initialize_logger(logger);  // applies the configured level for `name`
  return logger;
}

}  // namespace stage
