// The emergency stop (docs/operators.md#emergency-stop): every light node of the rig blacks out at once, and the stop
// stays latched (no take arms) until reset. Independent of recording: it works whatever the session is doing, with a
// channel to every light node made when the controller starts, so that no connection is set up when it matters.
#pragma once

#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/v1/controller.pb.h"
#include "stage/v1/rig.pb.h"

namespace grpc {
class Channel;
}

namespace stage::controller {

class EmergencyStop {
 public:
  explicit EmergencyStop(const v1::RigConfig& rig);
  ~EmergencyStop();

  // Latches, then tells every light node to black out, all at once, and answers when each has confirmed dark or
  // failed (the reply says which, and after how long).
  v1::EmergencyStopReply Stop(const std::string& reason);
  // Every light node leaves blackout; the latch is released when all did. FailedPrecondition names those that did
  // not (the latch stays).
  absl::StatusOr<v1::EmergencyStopReply> Reset();
  bool latched(std::string* reason = nullptr) const;

 private:
  v1::RigConfig rig_;
  std::vector<std::shared_ptr<grpc::Channel>> channels_;  // by light node, rig order
  mutable std::mutex mutex_;
  bool latched_ = false;  // guarded by mutex_
  std::string reason_;    // guarded by mutex_
};

}  // namespace stage::controller
