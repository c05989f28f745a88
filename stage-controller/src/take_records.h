// A take's records: its plan of slots (which slots each camera fires in, with a pause's gaps apart), each camera's
// account in the completeness ledger, the take's verdict (outcome and what to do about it), and what is kept of it:
// the take catalog (SQLite) and take.json in its directory (docs/storage.md). No node is reached from here: the
// session hands in what the nodes reported.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/storage/catalog.h"
#include "stage/timing/alignment.h"
#include "stage/v1/camera_node.pb.h"
#include "stage/v1/controller.pb.h"
#include "stage/v1/rig.pb.h"
#include "stage/v1/timing.pb.h"

namespace stage::controller {

// A take's gaps (pauses): slot ranges [first, end) of the take in which nothing fired.
using Gaps = std::vector<std::pair<int64_t, int64_t>>;

// The slots a camera fires in over a take of `slots` slots, with those in its gaps apart.
void CameraSlots(const v1::CameraTiming& timing, int64_t slots, const Gaps& gaps, std::vector<int64_t>* expected,
                 std::vector<int64_t>* paused);
// How many frames a camera owes a take of `slots` slots with `gaps`.
int64_t ExpectedFrames(const v1::CameraTiming& timing, int64_t slots, const Gaps& gaps);
// The progress entry of `role`, made on first use (in the order the roles come).
v1::RoleProgress* RoleOf(v1::CaptureProgress* progress, v1::CameraRole role);

// What the session knows of one camera once the take's cameras are finished.
struct CameraOutcome {
  const v1::CameraConfig* config = nullptr;
  const v1::CameraTiming* timing = nullptr;
  // Its report (Finish answered), or why there is none.
  std::optional<v1::CameraTakeReport> report;
  std::string error;
  // Its frame file, read when it did not report (what a node that died left).
  std::string path;
};

// The shape of a take as it ran.
struct TakeShape {
  int64_t slots = 0;  // its length, gaps included (0: it never ran)
  Gaps gaps;
  int64_t cycle = 38;
  bool ran = false;
  // The take slot where the slot clock stopped before the take's end (its generator was lost), -1: it did not. No
  // slot from there on fired: a frame not stored there is "sync generator lost", with `clock_lost` as its detail.
  int64_t clock_end = -1;
  std::string clock_lost;
};

// Accounts for one camera: its summary (counts, losses by pattern, the alignment self-test of a high-speed camera) in
// `summary`, an entry per expected slot in `ledger` (stored, or lost and why: what the camera reported, what its frame
// file holds, or the node that is gone). `say` hears what is worth telling the operator.
void AccountCamera(const TakeShape& take, const CameraOutcome& camera, const timing::Signature* signature,
                   v1::TakeSummary* summary, std::vector<storage::LedgerEntry>* ledger,
                   const std::function<void(const std::string&)>& say);

// Why a take did not end complete, beyond what its counts say.
struct TakeCircumstances {
  bool aborted = false;
  // Why it was aborted when not by the operator (a node lost, under controller.node_failure_policy: abort).
  std::string abort_reason;
  int64_t done_slots = 0;     // slots that ran (of an aborted take)
  int64_t capture_slots = 0;  // slots asked for
  std::vector<std::string> not_ready;
  std::string stalled;                    // nothing moved: why the take was given up
  std::string clock_lost;                 // the sync generator stopped before the take's end
  std::vector<std::string> light_faults;  // "node: fault"
};

// The take's outcome and its hint (what happened, what to do), into `summary` (its counts already in).
v1::TakeOutcome JudgeTake(const TakeShape& take, const TakeCircumstances& why, v1::TakeSummary* summary);

// The take catalog and every take's files.
class TakeRecords {
 public:
  static absl::StatusOr<std::unique_ptr<TakeRecords>> Open(std::string take_root);

  const std::string& take_root() const { return take_root_; }
  absl::StatusOr<std::string> NextTakeId(const std::string& stage_id, int64_t now_unix_ns);
  // The take's row in the catalog, and its take.json.
  absl::Status Create(const storage::TakeRow& row, const std::string& dir, const v1::RigConfig& rig,
                      const v1::Schedule& schedule, const v1::TakeSummary& summary);
  // Everything of a take that has ended: its ledger, its row, its take.json.
  absl::Status Keep(const storage::TakeRow& row, const std::vector<storage::LedgerEntry>& ledger,
                    const std::string& dir, const v1::RigConfig& rig, const v1::Schedule& schedule,
                    const v1::TakeSummary& summary);

  absl::StatusOr<v1::TakeList> ListTakes() const;
  // See Capturer::GetLedger and GetTake.
  absl::StatusOr<v1::LedgerPage> GetLedger(const v1::GetLedgerRequest& request) const;
  absl::StatusOr<v1::TakeSummary> GetTake(const std::string& id) const;

 private:
  // TakeRecord.processing from the take's processing/status.json.
  static void AddGraphStatus(const std::string& take_dir, v1::TakeRecord* t);
  TakeRecords() = default;
  // The id, with "latest" the newest take's.
  absl::StatusOr<storage::TakeRow> Row(const std::string& id) const;

  std::string take_root_;
  std::unique_ptr<storage::Catalog> catalog_;
};

// take.json: what the take was and how it ended (docs/storage.md).
absl::Status WriteTakeJson(const std::string& dir, const v1::RigConfig& rig, const v1::Schedule& schedule,
                           const v1::TakeSummary& summary, v1::TakeState state);

}  // namespace stage::controller
