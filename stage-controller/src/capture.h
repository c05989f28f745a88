// Capturing takes (docs/operators.md): the capture session and one take end to end. Arm every light node with its
// table and every camera node with its plan, run the sync generator (sync_generator.h) for the take's slots, watch
// progress and previews, pause, resume or abort on request (or when a node is lost and the rig's
// controller.node_failure_policy says abort), finish every camera, and keep the completeness ledger, the alignment
// self-test and the outcome (take_records.h).
//
// The session's states are stage.v1.SessionState; every change passes the one gate of session_state.h, is logged and
// announced (CaptureOptions.on_state_change, for watchers). The nodes and the generator are interfaces
// (node_clients.h, sync_generator.h): the controller's are gRPC clients, and the session's unit tests run a take in
// one process against fakes.
#pragma once

#include <chrono>
#include <condition_variable>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "emergency_stop.h"
#include "node_clients.h"
#include "session_state.h"
#include "stage/common/metrics.h"
#include "stage/common/rig.h"
#include "stage/timing/alignment.h"
#include "stage/v1/controller.pb.h"
#include "stage/v1/light_node.pb.h"
#include "stage/v1/timing.pb.h"
#include "sync_generator.h"
#include "take_events.h"
#include "take_records.h"
#include "take_watch.h"

namespace stage::controller {

struct CaptureOptions {
  // Where takes go (the catalog at its root); absolute.
  std::string take_root;
  // A take's frames may keep arriving this long after the last one came before the cameras are finished, ms.
  int drain_ms = 3'000;
  // How often the controller asks each camera for its latest preview during a take, ms.
  int preview_interval_ms = 500;
  // Longest side of a preview, px.
  uint32_t preview_size = 256;
  // How often the controller polls the cameras and the sync generator during a take, ms.
  int poll_interval_ms = 250;
  // Called after every change of the session's state (the stage's status watchers are woken).
  std::function<void()> on_state_change;
  // While it is latched no take arms. Not owned; may be null.
  const EmergencyStop* estop = nullptr;

  // InvalidArgument names the field: take_root empty or relative, a negative time, a zero interval or size.
  absl::Status Validate() const;
};

// What the session drives: the nodes, the sync generator (null: takes are refused, and the error says why), and the
// truth of a take beyond its frames (the simulator's; null on a real stage).
struct CaptureDevices {
  NodeClients nodes;
  std::unique_ptr<SyncGenerator> generator;
  // Why there is no generator, for the error (e.g. "timing.sync_generator names no light node").
  std::string no_generator;
  std::unique_ptr<TakeTruth> truth;
};

class Capturer {
 public:
  // `schedule`: the rig's compiled schedule (verified without errors, or Capture refuses).
  static absl::StatusOr<std::unique_ptr<Capturer>> Create(LoadedRig rig, v1::Schedule schedule, int timing_errors,
                                                          CaptureOptions options, CaptureDevices devices);
  ~Capturer();

  // Arms a take and leaves it armed for Capture (or Abort). FailedPrecondition unless idle (or error).
  absl::StatusOr<v1::TakeSummary> Arm(const v1::CaptureRequest& request, const CaptureEventFn& on_event);
  // Runs one take to its end, arming it first unless one is armed; `on_event` gets states, progress, the final counts
  // and the summary (last), every event with the take's id. FailedPrecondition while another take runs, naming its
  // state; InvalidArgument for no frames, or both frames and seconds.
  absl::StatusOr<v1::TakeSummary> Capture(const v1::CaptureRequest& request, const CaptureEventFn& on_event);
  // Follows the session's take (`take_id` empty, or its id) from now on: `fn` gets its events until Unfollow. The
  // snapshot says where the take stands (its latest state and progress, its summary once it has ended). NotFound when
  // the session holds no take, or another one than `take_id` (a take that has ended is the catalog's: GetTake).
  absl::StatusOr<TakeEvents::Joined> Follow(const std::string& take_id, CaptureEventFn fn);
  void Unfollow(int id) { events_.Unsubscribe(id); }
  // Pause at the next frame boundary, resume after it, abort (see controller.proto). FailedPrecondition names the
  // state when the request does not apply.
  absl::StatusOr<v1::SessionReply> Pause();
  absl::StatusOr<v1::SessionReply> Resume();
  absl::StatusOr<v1::SessionReply> Abort();

  // See the state list above.
  v1::SessionState state() const;
  // The take the session holds (from configuring to its end), or empty.
  std::string current_take_id() const;

  absl::StatusOr<v1::TakeList> ListTakes() const;
  // A page of a take's ledger (GetLedger in controller.proto). NotFound names an unknown take; InvalidArgument a bad
  // page token or size.
  absl::StatusOr<v1::LedgerPage> GetLedger(const v1::GetLedgerRequest& request) const;
  // A take by id, or "latest": the newest in the catalog. NotFound names an unknown id.
  absl::StatusOr<v1::TakeSummary> GetTake(const std::string& id) const;
  // The latest preview a camera sent during a take. NotFound before there is one, or for an unknown camera.
  absl::StatusOr<v1::Preview> GetPreview(const std::string& camera_id) const;

 private:
  struct Take;
  Capturer() = default;
  // The session's state changes through the gate (session_state.h): logged, the status watchers woken, the take's
  // followers told. A change the gate refuses is a defect of this class: logged as an error, the state stays.
  void SetState(v1::SessionState state);
  // Tells the take's followers and the log.
  void Say(const std::string& message, bool warn = false);
  // Claims the session for arming a take (mutex_ held): FailedPrecondition, `what` first, unless the session is idle
  // (or in error) and no other request is arming.
  absl::Status ClaimArming(const char* what);
  // ArmTake for a claimed session; the claim ends with it.
  absl::StatusOr<std::unique_ptr<Take>> ArmClaimed(const v1::CaptureRequest& request);
  // Creates the take and arms every node for it (state configuring, then armed).
  absl::StatusOr<std::unique_ptr<Take>> ArmTake(const v1::CaptureRequest& request);
  // Arms every light node with its table, and starts their heartbeat.
  void ArmLights(Take& take);
  // Arms every camera node with its plan (T0 comes when the take starts).
  void ArmCameras(Take& take);
  // Plans a run of the sync generator, tells every camera its T0 (and its plan), starts exactly that run: the run as
  // it started. `apply` records the planned run in the take (called under the session's lock) before the cameras hear
  // the plan; on an error the caller puts the take back as it was.
  absl::StatusOr<SyncRun> StartRun(Take& take, const SyncRunRequest& request,
                                   const std::function<void(const SyncRun&)>& apply);
  // A clock that runs free: every light node's table starts at the take's first edge (LightNode.StartTable).
  absl::Status StartLights(Take& take, int64_t first_edge_ns);
  // Starts the sync generator for the armed take; false when it could not start.
  bool StartTake(Take& take);
  // Watches progress (and previews) until every frame is in, or no more can come, or nothing moves for the stall
  // limit (take_watch.h); aborts the take when a node is lost and the rig's node_failure_policy says so.
  void WatchTake(Take& take);
  // Asks every armed camera how far it is, into `progress` (by role) and `snapshot`; fetches previews when due.
  void PollCameras(Take& take, int64_t slots, const Gaps& gaps, bool capturing, bool aborted,
                   v1::CaptureProgress* progress, TakeSnapshot* snapshot);
  // How far the sync generator has got with the take's current run, into `snapshot` (unset where it cannot say); a
  // generator that stopped answering for the drain, or ended its run before the take's end on its own, is lost.
  void ReadClock(Take& take, TakeSnapshot* snapshot);
  // The node (or the generator) the take has lost, in words; empty when none.
  std::string LostNode(Take& take, const TakeSnapshot& snapshot);
  // Finishes every camera, disarms the lights, keeps the ledger and the outcome.
  absl::StatusOr<v1::TakeSummary> FinalizeTake(Take& take);
  // Every armed camera's Finish, all at once, with the burst cameras' offload shown meanwhile: each camera's outcome.
  std::vector<CameraOutcome> FinishCameras(Take& take, const TakeShape& shape);
  // The lights' faults of the take (heartbeats and disarm), "node: fault" each; the lights are disarmed.
  std::vector<std::string> LightFaults(Take& take);
  // The simulator's truth of the frames that ran (not the pauses'), when there is a truth and the take asked for it.
  void WriteTruth(Take& take, const TakeShape& shape);
  // The take's final counts, once, then its summary.
  void EmitDone(Take& take, const std::vector<CameraOutcome>& cameras);
  // Sends every camera the take's current plan (its length and gaps; T0 once it starts).
  void UpdateCameras(Take& take, bool with_t0);
  absl::StatusOr<v1::TakeSummary> RunArmedTake(std::unique_ptr<Take> take);
  // Ends a capturing or paused take now (the operator's abort, or a lost node under the abort policy): the run ends
  // at the next slot where the generator can still be reached, the cameras are told, the session says aborting.
  absl::StatusOr<v1::SessionReply> AbortRunning(Take& take, v1::SessionState was, const std::string& why);
  // Disarms every light node (its last report of the take, or why it did not answer), then stops the heartbeat.
  struct LightDisarmed {
    v1::LightStats stats;
    std::string error;
  };
  std::vector<LightDisarmed> DisarmLights(Take& take);
  // When a request to a node that is slow to answer is given up: the stall limit from now (controller.take_stall_s).
  std::chrono::steady_clock::time_point StallDeadline() const;

  LoadedRig rig_;
  v1::Schedule schedule_;
  int timing_errors_ = 0;
  CaptureOptions options_;
  CaptureDevices devices_;
  timing::Signature signature_;
  bool have_signature_ = false;
  std::unique_ptr<TakeRecords> records_;

  // Pause, resume and abort one at a time (each talks to the generator and the cameras).
  std::mutex control_mutex_;
  mutable std::mutex mutex_;
  SessionMachine session_;    // guarded by mutex_
  std::string current_take_;  // guarded by mutex_
  bool arming_ = false;       // a request is arming a take (ClaimArming); guarded by mutex_
  TakeEvents events_;
  // The armed take no Capture has claimed yet (stagectl arm); guarded by mutex_.
  std::unique_ptr<Take> armed_;
  // The take being captured (owned by its Capture call); guarded by mutex_.
  Take* running_ = nullptr;
  std::map<std::string, v1::Preview> previews_;  // by camera id; guarded by mutex_
  // The session's state for the metrics (last: the collector goes before what it reads).
  metrics::Registration session_metrics_;
};

}  // namespace stage::controller
