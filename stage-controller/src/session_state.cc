// The session's one transition gate: see session_state.h.
#include "session_state.h"

#include "absl/strings/str_cat.h"
#include "stage/common/take_names.h"

namespace stage::controller {

bool SessionTransitionAllowed(v1::SessionState from, v1::SessionState to) {
  using S = v1::SessionState;
  if (from == to) return true;
  switch (from) {
    case S::SESSION_STATE_IDLE:
    case S::SESSION_STATE_ERROR:
      return to == S::SESSION_STATE_CONFIGURING;
    case S::SESSION_STATE_CONFIGURING:
      return to == S::SESSION_STATE_ARMED || to == S::SESSION_STATE_IDLE;
    case S::SESSION_STATE_ARMED:
      return to == S::SESSION_STATE_CAPTURING || to == S::SESSION_STATE_ABORTING || to == S::SESSION_STATE_FINALIZING;
    case S::SESSION_STATE_CAPTURING:
      return to == S::SESSION_STATE_PAUSED || to == S::SESSION_STATE_ABORTING || to == S::SESSION_STATE_FINALIZING;
    case S::SESSION_STATE_PAUSED:
      return to == S::SESSION_STATE_CAPTURING || to == S::SESSION_STATE_ABORTING || to == S::SESSION_STATE_FINALIZING;
    case S::SESSION_STATE_ABORTING:
    case S::SESSION_STATE_FINALIZING:
      return to == S::SESSION_STATE_IDLE || to == S::SESSION_STATE_ERROR;
    default:
      return false;
  }
}

absl::StatusOr<bool> SessionMachine::Transition(v1::SessionState to) {
  if (!SessionTransitionAllowed(state_, to)) {
    return absl::FailedPreconditionError(
        absl::StrCat("the session cannot go from ", SessionStateName(state_), " to ", SessionStateName(to)));
  }
  if (state_ == to) return false;
  state_ = to;
  return true;
}

}  // namespace stage::controller
