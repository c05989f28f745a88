// Words for the take.proto enums in messages, logs and tables (the wire and --json carry the enums themselves):
// "capturing", "COMPLETE", "offloading".
#pragma once

#include <string>

#include "stage/v1/take.pb.h"

namespace stage {

// The session's state in lower case: "idle", "capturing", "finalizing", ...
std::string SessionStateName(v1::SessionState state);
// A take's outcome as the catalog and the operator see it: "COMPLETE", "DEGRADED", "FAILED"; "" before it ends.
std::string TakeOutcomeName(v1::TakeOutcome outcome);
// "capturing", "paused", "aborting", "offloading", "done".
std::string CapturePhaseName(v1::CapturePhase phase);
// A take's state in the catalog: "configuring", "complete", "degraded", "failed", "aborted".
std::string TakeStateName(v1::TakeState state);
// Why a frame is not stored, in words: "stored", "camera dropped", "trigger missed", "not delivered", ...
std::string LossReasonName(v1::LossReason reason);

}  // namespace stage
