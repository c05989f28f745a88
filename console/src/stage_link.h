// The console's link to the stage: a gRPC client of the controller and nothing else, so a console that fails never
// touches the stage. It follows the stage's status (WatchStageStatus) and the take the session holds (WatchTake), and
// publishes both on the event log, raising and clearing alarms from each status; commands and reads are one call each.
#pragma once

#include <atomic>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "alarms.h"
#include "event_log.h"

namespace grpc {
class ClientContext;
}

namespace stage::console {

struct StageLinkOptions {
  // The controller, host:port.
  std::string controller;
  // Deadline of a command or a read, ms.
  int call_timeout_ms = 10000;
  // Time between tries to reach a controller that does not answer, ms.
  int retry_ms = 1000;
  AlarmThresholds alarms;

  // InvalidArgument naming the field.
  absl::Status Validate() const;
};

// What a command or read answers: JSON (the contract's mapping of the reply), or bytes of another type (a preview PNG,
// the timing SVG).
struct Reply {
  std::string content_type = "application/json";
  std::string body;
};

class StageLink {
 public:
  // `events` and `alarms` are not owned and must outlive the link.
  StageLink(StageLinkOptions options, EventLog* events, AlarmBook* alarms);
  ~StageLink();

  // Starts following the stage. Call once.
  void Start();
  void Stop();

  // The latest status as JSON ("{}" before the first) and whether the controller answers now.
  std::string LatestStatusJson() const;
  bool connected() const { return connected_.load(); }

  // Session commands. Arm and Capture take a CaptureRequest as JSON (the contract's mapping; "{}" for the rig's
  // defaults) and answer once the controller has taken the request (its first event), not at the take's end: the take
  // runs on, followed on the event stream.
  absl::StatusOr<Reply> Arm(const std::string& request_json);
  absl::StatusOr<Reply> Capture(const std::string& request_json);
  absl::StatusOr<Reply> Pause();
  absl::StatusOr<Reply> Resume();
  absl::StatusOr<Reply> Abort();
  absl::StatusOr<Reply> EmergencyStop(const std::string& reason);
  absl::StatusOr<Reply> ResetEmergencyStop();

  // Reads.
  // The camera's latest preview: {"width", "height", "frame": the frame's metadata, "png": base64}.
  absl::StatusOr<Reply> Preview(const std::string& camera_id);
  absl::StatusOr<Reply> Takes();
  absl::StatusOr<Reply> Take(const std::string& take_id);
  absl::StatusOr<Reply> Ledger(const std::string& take_id, bool lost_only, int page_size,
                               const std::string& page_token);
  absl::StatusOr<Reply> Timing();
  absl::StatusOr<Reply> TimingSvg();

 private:
  struct Impl;
  void FollowStatus();
  void FollowTake(const std::string& take_id);
  absl::StatusOr<Reply> StartTake(bool capture, const std::string& request_json);

  StageLinkOptions options_;
  EventLog* events_;
  AlarmBook* alarms_;
  std::unique_ptr<Impl> impl_;
  std::atomic<bool> connected_{false};
  std::atomic<bool> stopping_{false};
  std::thread status_thread_;
};

}  // namespace stage::console
