// absl::Status helpers used across FaStage: early-return macros and errno conversion.
#pragma once

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

// Returns from the enclosing function if `expr` (an absl::Status) is not OK.
#define STAGE_RETURN_IF_ERROR(expr)                \
  do {                                             \
    ::absl::Status stage_status_ = (expr);         \
    if (!stage_status_.ok()) return stage_status_; \
  } while (false)

#define STAGE_STATUS_CONCAT_INNER_(a, b) a##b
#define STAGE_STATUS_CONCAT_(a, b) STAGE_STATUS_CONCAT_INNER_(a, b)

// `STAGE_ASSIGN_OR_RETURN(auto x, F());` declares x from an absl::StatusOr, or returns its error.
#define STAGE_ASSIGN_OR_RETURN(lhs, expr) \
  STAGE_ASSIGN_OR_RETURN_IMPL_(STAGE_STATUS_CONCAT_(stage_statusor_, __LINE__), lhs, expr)
#define STAGE_ASSIGN_OR_RETURN_IMPL_(tmp, lhs, expr) \
  auto tmp = (expr);                                 \
  if (!tmp.ok()) return tmp.status();                \
  lhs = std::move(tmp).value()

namespace stage {

// An error for a failed system call: "<what>: <strerror(errno_value)>", with a code chosen from the errno.
absl::Status ErrnoToStatus(int errno_value, absl::string_view what);

// Prefixes a non-OK status's message with `context` ("<context>: <message>"), keeping its code.
absl::Status Annotate(const absl::Status& status, absl::string_view context);

}  // namespace stage
