// The project's one JSON convention for its messages (`--json` of every program, take.json, the endpoint file):
// protobuf's JSON mapping of the stage.v1 message, with the proto field names (snake_case), every field present
// (defaults too: false, 0, ""; a sub-message that is not set is left out), 64-bit integers as strings, enums by their
// names ("SESSION_STATE_IDLE"), indented. Any protobuf library parses it back (docs/contract.md).
#pragma once

#include <string>

#include "absl/status/status.h"

namespace google::protobuf {
class Message;
}

namespace stage {

std::string ToContractJson(const google::protobuf::Message& message);
// The reverse, ignoring fields this build does not know (a newer writer). InvalidArgument says why.
absl::Status FromContractJson(const std::string& json, google::protobuf::Message* message);

}  // namespace stage
