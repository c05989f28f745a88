// Capturing takes (docs/operators.md): the session state machine and one take end to end. Arm every light node with
// its table and every camera node with its plan, run the sync generator (the simulated world's bus; a hardware slot
// clock later) for the take's slots, watch progress, finish every camera, and keep the completeness ledger, the
// alignment self-test and the outcome in the take catalog and in take.json.
#pragma once

#include <atomic>
#include <functional>
#include <memory>
#include <mutex>
#include <string>

#include "absl/status/statusor.h"
#include "stage/common/rig.h"
#include "stage/storage/catalog.h"
#include "stage/timing/alignment.h"
#include "stage/v1/controller.pb.h"
#include "stage/v1/timing.pb.h"

namespace stage::controller {

struct CaptureOptions {
  // Where takes go (the catalog at its root); absolute.
  std::string take_root;
  // host:port of the simulated world's SimWorld (the sync generator in the simulator); empty: none.
  std::string world_address;
  // Deadline of each node's Arm, ms.
  int arm_timeout_ms = 10'000;
  // A take's frames may keep arriving this long after the last one came before the cameras are finished, ms.
  int drain_ms = 3'000;
};

class Capturer {
 public:
  // `schedule`: the rig's compiled schedule (verified without errors, or Capture refuses).
  static absl::StatusOr<std::unique_ptr<Capturer>> Create(LoadedRig rig, v1::Schedule schedule, int timing_errors,
                                                          CaptureOptions options);

  // Runs one take; `on_event` gets states, progress and the summary (last). FailedPrecondition while another take
  // runs, naming its state.
  absl::StatusOr<v1::TakeSummary> Capture(const v1::CaptureRequest& request,
                                          const std::function<void(const v1::CaptureEvent&)>& on_event);

  // "idle", "configuring", "armed", "capturing", "finalizing".
  std::string state() const;
  absl::StatusOr<v1::TakeList> ListTakes() const;
  absl::StatusOr<v1::TakeSummary> GetTake(const std::string& id) const;

 private:
  Capturer() = default;
  void SetState(const std::string& state, const std::function<void(const v1::CaptureEvent&)>& on_event);
  LoadedRig rig_;
  v1::Schedule schedule_;
  int timing_errors_ = 0;
  CaptureOptions options_;
  timing::Signature signature_;
  bool have_signature_ = false;
  std::unique_ptr<storage::Catalog> catalog_;
  mutable std::mutex mutex_;
  std::string state_ = "idle";  // guarded by mutex_
};

}  // namespace stage::controller
