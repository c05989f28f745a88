// Small file helpers shared by programs that hand files to each other (port files, endpoint files, rigs).
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace stage {

// The whole file. On failure the message is "<path>: cannot read <what>: <reason>" with a code from the errno
// (NotFound, PermissionDenied, ...).
absl::StatusOr<std::string> ReadFileToString(const std::string& path, absl::string_view what = "file");

// Writes `text` to `path` atomically (a temporary file beside it, then rename), so a reader polling for the file never
// sees it half written.
absl::Status WriteFileAtomically(const std::string& path, const std::string& text);

}  // namespace stage
