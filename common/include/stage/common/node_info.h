// Building the NodeInfo every service returns from GetInfo.
#pragma once

#include <string>

#include "stage/v1/node.pb.h"

namespace stage {

// Fills id, kind, a camera's role, backend and rig hash as given, and version, pid, hostname and uptime from this
// process.
v1::NodeInfo MakeNodeInfo(const std::string& id, v1::NodeKind kind, v1::CameraRole role, const std::string& backend,
                          const std::string& rig_hash);

// This machine's host name ("" if it has none).
std::string HostName();

// "camera", "light", "processing-worker", "controller".
std::string NodeKindName(v1::NodeKind kind);
// "up", "down", "unreachable", "unknown".
std::string NodeStateName(v1::NodeState state);

}  // namespace stage
