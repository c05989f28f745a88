// Small file helpers shared by programs that hand files to each other (port files, endpoint files, rigs).
#pragma once

#include <string>

#include "absl/status/statusor.h"

namespace stage {

// The whole file; NotFound / PermissionDenied naming the path on failure.
absl::StatusOr<std::string> ReadFileToString(const std::string& path);

// Writes `text` to `path` atomically (a temporary file beside it, then rename), so a reader polling for the file never
// sees it half written.
absl::Status WriteFileAtomically(const std::string& path, const std::string& text);

}  // namespace stage
