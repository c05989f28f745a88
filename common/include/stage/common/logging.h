// spdlog setup: one stderr sink shared by named loggers ("camera.sim", "controller.health", ...), levels from
// SPDLOG_LEVEL (e.g. "info,camera.sim=debug") and from a program's --log-level flag (same syntax, wins).
#pragma once

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "spdlog/logger.h"

// absl::string_view is its own type in Debian's Abseil (not std::string_view): teach fmt/spdlog to print it.
template <>
struct fmt::formatter<absl::string_view> : fmt::formatter<fmt::string_view> {
  template <typename FormatContext>
  auto format(absl::string_view s, FormatContext& ctx) const {
    return fmt::formatter<fmt::string_view>::format(fmt::string_view(s.data(), s.size()), ctx);
  }
};

namespace stage {

// Sets up logging for `program` (its name appears in every line). Call once at the start of main(). `levels` is the
// --log-level value ("" to use SPDLOG_LEVEL alone); an invalid level is an error naming it.
absl::Status InitLogging(absl::string_view program, absl::string_view levels);

// The logger named `name`, created on first use with the shared sink and the configured level. Thread-safe.
std::shared_ptr<spdlog::logger> Logger(const std::string& name);

// Checks a level spec ("debug", "info,camera.sim=trace") without applying it.
absl::Status ValidateLogLevels(absl::string_view levels);

}  // namespace stage
