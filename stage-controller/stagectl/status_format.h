// How stagectl shows stage status: a table a person reads at a glance. (For scripts, `--json` prints the StageStatus
// message itself in the project's JSON convention: stage/common/proto_json.h.)
#pragma once

#include <cstdint>
#include <string>

#include "stage/v1/controller.pb.h"

namespace stage::stagectl {

// The status table. `now_unix_ns` is used for "last seen ... ago". `color` adds ANSI colours to the state column.
std::string FormatStatusTable(const v1::StageStatus& status, int64_t now_unix_ns, bool color);

}  // namespace stage::stagectl
