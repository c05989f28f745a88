// How stagectl shows stage status: a table a person reads at a glance, and JSON for scripts.
#pragma once

#include <cstdint>
#include <string>

#include "stage/v1/controller.pb.h"

namespace stage::stagectl {

// The status table. `now_unix_ns` is used for "last seen ... ago". `color` adds ANSI colours to the state column.
std::string FormatStatusTable(const v1::StageStatus& status, int64_t now_unix_ns, bool color);

// JSON (one object): {"stage": {...}, "controller": {...}, "summary": {...}, "nodes": [{...}, ...]}, with states
// and kinds as words ("up", "camera") and times in ns. docs/operators.md documents the fields.
std::string StatusToJson(const v1::StageStatus& status);

}  // namespace stage::stagectl
