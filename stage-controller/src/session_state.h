// The capture session's state machine: the states are stage.v1.SessionState, and every change passes one gate that
// knows which changes exist (docs/operators.md draws them):
//
//   idle, error -> configuring -> armed -> capturing <-> paused
//   configuring -> idle                      (arming failed: no take)
//   armed, capturing, paused -> aborting     (the operator stops the take)
//   armed, capturing, paused -> finalizing   (the take ends: every frame in, nothing more can come, or nothing started)
//   aborting, finalizing -> idle             (the take is kept)
//   aborting, finalizing -> error            (its records could not be kept; the next take may start from there)
#pragma once

#include "absl/status/statusor.h"
#include "stage/v1/take.pb.h"

namespace stage::controller {

// Whether the session may go from `from` to `to` (a state to itself is no change, and allowed).
bool SessionTransitionAllowed(v1::SessionState from, v1::SessionState to);

// Not thread-safe: its owner guards it.
class SessionMachine {
 public:
  v1::SessionState state() const { return state_; }
  // Moves to `to`: true when the state changed, false when it already was `to`. FailedPrecondition naming both states
  // for a change the machine does not have (the state stays).
  absl::StatusOr<bool> Transition(v1::SessionState to);

 private:
  v1::SessionState state_ = v1::SESSION_STATE_IDLE;
};

}  // namespace stage::controller
