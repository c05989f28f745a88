// The take catalog and the completeness ledger: one SQLite database at the take root (`<root>/catalog.sqlite`,
// docs/storage.md). The catalog lists every take with its state, duration, size and outcome; the ledger holds, for
// every expected (camera, slot) of a take, its outcome: stored (with the camera's frame id), or lost with a reason.
// WAL mode: stagectl and the console read while the controller writes.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/v1/take.pb.h"

struct sqlite3;

namespace stage::storage {

struct TakeRow {
  std::string id;    // e.g. "fastage-20261123-0001"
  std::string name;  // the operator's name for it, or empty
  // The column holds TakeStateText: "configuring", then "complete", "degraded", "failed" or "aborted".
  v1::TakeState state = v1::TAKE_STATE_CONFIGURING;
  int64_t created_unix_ns = 0;
  int64_t t0_unix_ns = 0;  // slot 0, controller time; 0 before arming
  int64_t slots = 0;       // slots requested
  double duration_s = 0;   // of the stage, slots / slot rate
  int64_t size_bytes = 0;  // on disk, once finalized
  int64_t frames_expected = 0;
  int64_t frames_stored = 0;
  // Once finalized; the column holds TakeOutcomeText: "COMPLETE", "DEGRADED" or "FAILED" ("" before).
  v1::TakeOutcome outcome = v1::TAKE_OUTCOME_UNSPECIFIED;
  std::string rig_hash;
  std::string schedule_hash;
  std::string dir;  // relative to the take root
};

// The take.proto enums in the catalog's text columns: "complete" (state), "COMPLETE" (outcome; "" unspecified), and
// back; InvalidArgument for text no enum value has.
std::string TakeStateText(v1::TakeState state);
std::string TakeOutcomeText(v1::TakeOutcome outcome);
absl::StatusOr<v1::TakeState> TakeStateFromText(const std::string& text);
absl::StatusOr<v1::TakeOutcome> TakeOutcomeFromText(const std::string& text);

// Why an expected frame is not stored: v1::LossReason (take.proto, the one definition, whose numbers the ledger
// stores), as a scoped enum for this code.
enum class LossReason {
  kNone = v1::LOSS_REASON_STORED,
  kCameraDropped = v1::LOSS_REASON_CAMERA_DROPPED,
  kTriggerMissed = v1::LOSS_REASON_TRIGGER_MISSED,
  kNodeDown = v1::LOSS_REASON_NODE_DOWN,
  kLate = v1::LOSS_REASON_LATE,
  kWriteFailed = v1::LOSS_REASON_WRITE_FAILED,
  kIncomplete = v1::LOSS_REASON_INCOMPLETE,
  kPaused = v1::LOSS_REASON_PAUSED,
  kLinkDown = v1::LOSS_REASON_LINK_DOWN,
  kNotDelivered = v1::LOSS_REASON_NOT_DELIVERED,
  kSyncGeneratorLost = v1::LOSS_REASON_SYNC_GENERATOR_LOST,
};
inline v1::LossReason ToProto(LossReason r) { return static_cast<v1::LossReason>(r); }
inline LossReason FromProto(v1::LossReason r) { return static_cast<LossReason>(r); }
std::string LossReasonName(LossReason reason);  // in words: "stored", "camera dropped", "trigger missed", ...

struct LedgerEntry {
  std::string camera_id;
  int64_t slot = 0;
  int32_t pattern = 0;
  LossReason reason = LossReason::kNone;
  std::optional<uint64_t> frame_id;  // the camera's frame counter, when it delivered one
  std::string detail;                // e.g. the write error
  bool stored() const { return reason == LossReason::kNone; }
};

// Counts of a take's ledger, per camera and per pattern.
struct LedgerCounts {
  int64_t expected = 0;
  int64_t stored = 0;
  std::map<LossReason, int64_t> lost;  // by reason
};
struct LedgerSummary {
  LedgerCounts total;
  std::map<std::string, LedgerCounts> by_camera;
  std::map<int32_t, LedgerCounts> by_pattern;
};

class Catalog {
 public:
  // Opens (creating if needed) the catalog of take root `root`; errors name the file.
  static absl::StatusOr<std::unique_ptr<Catalog>> Open(const std::string& root);
  ~Catalog();
  const std::string& path() const { return path_; }

  // A new take (ALREADY_EXISTS if its id is taken).
  absl::Status CreateTake(const TakeRow& take);
  // Replaces the take's row (NOT_FOUND names an unknown id).
  absl::Status UpdateTake(const TakeRow& take);
  absl::StatusOr<TakeRow> GetTake(const std::string& id) const;
  // Every take, oldest first.
  absl::StatusOr<std::vector<TakeRow>> ListTakes() const;
  // The next free take id of stage `stage_id` on the day of `unix_ns` (local calendar): "<stage>-YYYYMMDD-NNNN".
  absl::StatusOr<std::string> NextTakeId(const std::string& stage_id, int64_t unix_ns) const;

  // Records ledger entries of a take in one transaction; an entry for a (camera, slot) already in the ledger
  // replaces it.
  absl::Status RecordLedger(const std::string& take_id, const std::vector<LedgerEntry>& entries);
  // The take's ledger, by camera then slot; `camera_id` non-empty: that camera's only.
  absl::StatusOr<std::vector<LedgerEntry>> Ledger(const std::string& take_id, const std::string& camera_id = "") const;
  // One page of it: `limit` entries from `offset` (in the same order), those of `camera_id` (empty: every camera),
  // lost ones only if `lost_only` (neither stored nor paused); and how many match in all.
  struct LedgerPage {
    std::vector<LedgerEntry> entries;
    int64_t total = 0;
  };
  absl::StatusOr<LedgerPage> ReadLedgerPage(const std::string& take_id, const std::string& camera_id, bool lost_only,
                                            int64_t offset, int64_t limit) const;
  absl::StatusOr<LedgerSummary> Summarize(const std::string& take_id) const;

 private:
  Catalog() = default;
  absl::Status Exec(const char* sql) const;
  absl::Status Error(const std::string& what) const;
  std::string path_;
  sqlite3* db_ = nullptr;
};

}  // namespace stage::storage
