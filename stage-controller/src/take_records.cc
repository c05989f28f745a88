// A take's plan of slots, its ledger, its verdict and its records: see take_records.h.
#include "take_records.h"

#include <algorithm>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/file_util.h"
#include "stage/common/ledger_counts.h"
#include "stage/common/logging.h"
#include "stage/common/processing_names.h"
#include "stage/common/proto_json.h"
#include "stage/common/status.h"
#include "stage/common/take_names.h"
#include "stage/common/version.h"
#include "stage/storage/frame_file.h"
#include "stage/timing/schedule.h"

namespace stage::controller {
namespace {

namespace fs = std::filesystem;

bool InGap(const Gaps& gaps, int64_t slot) {
  for (const auto& [first, end] : gaps) {
    if (slot >= first && slot < end) return true;
  }
  return false;
}

// Counts one ledger entry into `c`: a paused slot is neither expected nor lost.
void Count(v1::LedgerCounts* c, storage::LossReason reason) {
  if (reason == storage::LossReason::kPaused) {
    c->set_paused(c->paused() + 1);
    return;
  }
  c->set_expected(c->expected() + 1);
  if (reason == storage::LossReason::kNone) {
    c->set_stored(c->stored() + 1);
  } else {
    AddLoss(c, storage::ToProto(reason));
  }
}

// What a camera's node left in its frame file (it did not report): its slots, by slot.
std::map<int64_t, storage::LedgerEntry> Recover(const CameraOutcome& camera, v1::CameraTakeSummary* cs,
                                                const std::function<void(const std::string&)>& say) {
  std::map<int64_t, storage::LedgerEntry> known;
  auto file = storage::FrameFileReader::Open(camera.path);
  auto records = file.ok() ? (*file)->Records() : absl::StatusOr<std::vector<storage::FrameRecord>>(file.status());
  if (!records.ok()) return known;
  cs->set_path(camera.path);
  // The writer died with space reserved ahead of its frames: give it back, so the file holds what it says.
  if (absl::Status s = storage::ReleaseReservedSpace(camera.path); !s.ok()) say(std::string(s.message()));
  std::error_code ec;
  cs->set_bytes(fs::file_size(camera.path, ec));
  for (const storage::FrameRecord& r : *records) {
    if (r.status != storage::FrameStatus::kOk && r.status != storage::FrameStatus::kIncomplete) continue;
    known[r.slot] = {
        camera.config->id(),
        r.slot,
        r.pattern,
        r.status == storage::FrameStatus::kOk ? storage::LossReason::kNone : storage::LossReason::kIncomplete,
        r.frame_id,
        "in the frame file the node left"};
  }
  say(absl::StrCat(camera.config->id(), " did not report (", cs->error(), "): ", known.size(),
                   " frames recovered from ", camera.path));
  return known;
}

}  // namespace

void CameraSlots(const v1::CameraTiming& timing, int64_t slots, const Gaps& gaps, std::vector<int64_t>* expected,
                 std::vector<int64_t>* paused) {
  const int64_t d = std::max<uint32_t>(1, timing.divider());
  for (int64_t k = timing.slot_phase(); k < slots; k += d) (InGap(gaps, k) ? paused : expected)->push_back(k);
}

int64_t ExpectedFrames(const v1::CameraTiming& timing, int64_t slots, const Gaps& gaps) {
  int64_t n = timing::FiringsInTake(timing, slots);
  const int64_t d = std::max<uint32_t>(1, timing.divider()), p = timing.slot_phase();
  auto before = [&](int64_t s) { return s > p ? (s - p - 1) / d + 1 : 0; };  // firings in [0, s)
  for (const auto& [first, end] : gaps) n -= before(std::min(end, slots)) - before(std::min(first, slots));
  return n;
}

v1::RoleProgress* RoleOf(v1::CaptureProgress* progress, v1::CameraRole role) {
  for (v1::RoleProgress& r : *progress->mutable_roles()) {
    if (r.role() == role) return &r;
  }
  v1::RoleProgress* r = progress->add_roles();
  r->set_role(role);
  return r;
}

void AccountCamera(const TakeShape& take, const CameraOutcome& camera, const timing::Signature* signature,
                   v1::TakeSummary* summary, std::vector<storage::LedgerEntry>* ledger,
                   const std::function<void(const std::string&)>& say) {
  const std::string& id = camera.config->id();
  v1::CameraTakeSummary* cs = summary->add_cameras();
  cs->set_camera_id(id);
  cs->set_role(camera.config->role());
  auto add = [&](storage::LedgerEntry e) {
    Count(cs->mutable_counts(), e.reason);
    Count(summary->mutable_total(), e.reason);
    ledger->push_back(std::move(e));
  };
  std::vector<int64_t> expected, in_gaps;
  CameraSlots(*camera.timing, take.slots, take.gaps, &expected, &in_gaps);
  for (int64_t k : in_gaps) {
    add({id, k, static_cast<int32_t>(k % take.cycle), storage::LossReason::kPaused, std::nullopt,
         "the take was paused"});
  }
  // What the camera says of each slot; a node that cannot report leaves what its file holds.
  std::map<int64_t, storage::LedgerEntry> known;
  if (camera.report) {
    const v1::CameraTakeReport& report = *camera.report;
    cs->set_path(report.path());
    cs->set_bytes(report.bytes());
    cs->set_error(report.error());
    for (const v1::SlotRecord& r : report.slots()) {
      known[r.slot()] = {id,
                         r.slot(),
                         r.pattern(),
                         static_cast<storage::LossReason>(r.reason()),
                         r.has_frame_id() ? std::optional<uint64_t>(r.frame_id()) : std::nullopt,
                         r.detail()};
    }
  } else if (take.ran) {
    cs->set_error(camera.error.empty() ? "did not report" : camera.error);
    known = Recover(camera, cs, say);
  }
  summary->set_bytes(summary->bytes() + cs->bytes());
  const size_t first_entry = ledger->size();
  for (int64_t k : expected) {
    auto it = known.find(k);
    const bool stored = it != known.end() && it->second.stored();
    if (take.clock_end >= 0 && k >= take.clock_end && !stored) {
      add({id, k, static_cast<int32_t>(k % take.cycle), storage::LossReason::kSyncGeneratorLost, std::nullopt,
           take.clock_lost});
    } else if (it != known.end() && it->second.reason != storage::LossReason::kPaused) {
      add(it->second);
    } else {
      add({id, k, static_cast<int32_t>(k % take.cycle), storage::LossReason::kNodeDown, std::nullopt,
           camera.report ? "not in the camera's report" : cs->error()});
    }
  }
  std::vector<int64_t> lost_by_pattern(static_cast<size_t>(take.cycle), 0);
  for (size_t j = first_entry; j < ledger->size(); ++j) {
    const storage::LedgerEntry& e = (*ledger)[j];
    if (!e.stored()) {
      ++lost_by_pattern[static_cast<size_t>(e.pattern) % lost_by_pattern.size()];
    }
  }
  for (int64_t n : lost_by_pattern) cs->add_lost_by_pattern(n);
  if (camera.report && camera.config->role() == v1::CAMERA_ROLE_HIGH_SPEED && signature != nullptr && take.ran) {
    const v1::CameraTakeReport& report = *camera.report;
    std::map<int64_t, double> brightness;
    for (int j = 0; j < report.brightness_slots_size() && j < report.brightness_size(); ++j) {
      brightness[report.brightness_slots(j)] = report.brightness(j);
    }
    const timing::AlignmentReport a = timing::CheckAlignment(*signature, static_cast<int>(take.cycle), brightness);
    v1::AlignmentSummary* as = summary->add_alignment();
    as->set_camera_id(id);
    as->set_ok(a.ok);
    as->set_shift(a.shift);
    as->set_residual(a.residual);
    for (int64_t b : a.bad_cycles) as->add_bad_cycles(b);
    as->set_message(a.message);
  }
}

v1::TakeOutcome JudgeTake(const TakeShape& take, const TakeCircumstances& why, v1::TakeSummary* summary) {
  std::vector<std::string> hints;
  if (why.aborted) {
    const std::string by = why.abort_reason.empty()
                               ? "by the operator"
                               : absl::StrCat("(", why.abort_reason, "; controller.node_failure_policy: abort)");
    const int64_t at = take.clock_end >= 0 ? take.clock_end : take.slots;
    hints.push_back(take.ran ? absl::StrCat("aborted ", by, " at slot ", at, " (", why.done_slots / take.cycle, " of ",
                                            why.capture_slots / take.cycle, " frames ran); what was recorded is kept")
                             : absl::StrCat("aborted ", by, " before it started"));
  }
  if (!take.ran && !why.aborted) {
    hints.push_back(why.not_ready.empty() ? "the sync generator never ran"
                                          : absl::StrCat("not ready: ", absl::StrJoin(why.not_ready, ", ")));
  }
  if (!why.clock_lost.empty()) hints.push_back(absl::StrCat("the sync generator was lost: ", why.clock_lost));
  if (!why.stalled.empty()) hints.push_back(absl::StrCat("the take stalled: ", why.stalled));
  bool aligned = true;
  for (const auto& a : summary->alignment()) {
    if (!a.ok()) {
      aligned = false;
      hints.push_back(absl::StrCat(a.camera_id(), ": ", a.message()));
    }
  }
  for (const auto& cs : summary->cameras()) {
    const int64_t lost = cs.counts().expected() - cs.counts().stored();
    if (lost <= 0) continue;
    std::vector<std::string> reasons;
    for (const v1::LossCount& l : cs.counts().lost()) {
      reasons.push_back(absl::StrCat(l.frames(), " ", LossReasonName(l.reason())));
    }
    hints.push_back(absl::StrCat(cs.camera_id(), " lost ", lost, " (", absl::StrJoin(reasons, ", "), ")"));
  }
  // A light node that faulted during the take (a board that stopped answering, over temperature): its frames may be
  // lit wrong even where they are all stored.
  hints.insert(hints.end(), why.light_faults.begin(), why.light_faults.end());
  const v1::LedgerCounts& total = summary->total();
  v1::TakeOutcome outcome = v1::TAKE_OUTCOME_COMPLETE;
  if (!take.ran || why.aborted || total.stored() == 0) {
    outcome = v1::TAKE_OUTCOME_FAILED;
  } else if (total.stored() < total.expected() || !aligned || !why.light_faults.empty() || !why.clock_lost.empty()) {
    outcome = v1::TAKE_OUTCOME_DEGRADED;
  }
  summary->set_outcome(outcome);
  if (!hints.empty()) {
    if (hints.size() > 6) {
      const size_t more = hints.size() - 5;
      hints.resize(5);
      hints.push_back(absl::StrCat("and ", more, " more"));
    }
    summary->set_hint(absl::StrCat(outcome == v1::TAKE_OUTCOME_COMPLETE ? "" : "retake? ", absl::StrJoin(hints, "; ")));
  }
  return outcome;
}

absl::Status WriteTakeJson(const std::string& dir, const v1::RigConfig& rig, const v1::Schedule& schedule,
                           const v1::TakeSummary& summary, v1::TakeState state) {
  std::string text = absl::StrCat(
      "{\n\"format\": \"fastage-take-1\",\n\"software\": \"FaStage ", kVersion, "\",\n\"state\": \"",
      storage::TakeStateText(state), "\",\n\"schedule_hash\": \"", schedule.hash(), "\",\n\"rig_hash\": \"",
      schedule.rig_hash(), "\",\n\"summary\": ", ToContractJson(summary), ",\n\"rig\": ", ToContractJson(rig), "\n}\n");
  return WriteFileAtomically(dir + "/take.json", text);  // a reader sees the old file or the new one
}

absl::StatusOr<std::unique_ptr<TakeRecords>> TakeRecords::Open(std::string take_root) {
  std::unique_ptr<TakeRecords> r(new TakeRecords());
  STAGE_ASSIGN_OR_RETURN(r->catalog_, storage::Catalog::Open(take_root));
  r->take_root_ = std::move(take_root);
  return r;
}

absl::StatusOr<std::string> TakeRecords::NextTakeId(const std::string& stage_id, int64_t now_unix_ns) {
  return catalog_->NextTakeId(stage_id, now_unix_ns);
}

absl::Status TakeRecords::Create(const storage::TakeRow& row, const std::string& dir, const v1::RigConfig& rig,
                                 const v1::Schedule& schedule, const v1::TakeSummary& summary) {
  STAGE_RETURN_IF_ERROR(catalog_->CreateTake(row));
  return WriteTakeJson(dir, rig, schedule, summary, row.state);
}

absl::Status TakeRecords::Keep(const storage::TakeRow& row, const std::vector<storage::LedgerEntry>& ledger,
                               const std::string& dir, const v1::RigConfig& rig, const v1::Schedule& schedule,
                               const v1::TakeSummary& summary) {
  STAGE_RETURN_IF_ERROR(catalog_->RecordLedger(row.id, ledger));
  STAGE_RETURN_IF_ERROR(catalog_->UpdateTake(row));
  return WriteTakeJson(dir, rig, schedule, summary, row.state);
}

absl::StatusOr<storage::TakeRow> TakeRecords::Row(const std::string& id) const {
  if (id != "latest") return catalog_->GetTake(id);
  // The newest take in the catalog (ListTakes is oldest first).
  STAGE_ASSIGN_OR_RETURN(std::vector<storage::TakeRow> rows, catalog_->ListTakes());
  if (rows.empty()) return absl::NotFoundError(absl::StrCat("no take yet in ", take_root_));
  return rows.back();
}

absl::StatusOr<v1::LedgerPage> TakeRecords::GetLedger(const v1::GetLedgerRequest& request) const {
  constexpr int kDefaultPage = 1000, kMaxPage = 10000;
  if (request.page_size() < 0 || request.page_size() > kMaxPage) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_size ", request.page_size(), " is not in 0..", kMaxPage, " (0: ", kDefaultPage, ")"));
  }
  int64_t offset = 0;
  if (!request.page_token().empty() && (!absl::SimpleAtoi(request.page_token(), &offset) || offset < 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_token \"", request.page_token(), "\" is not one this controller gave"));
  }
  STAGE_ASSIGN_OR_RETURN(const storage::TakeRow row, Row(request.take_id()));
  const int64_t size = request.page_size() > 0 ? request.page_size() : kDefaultPage;
  STAGE_ASSIGN_OR_RETURN(storage::Catalog::LedgerPage rows,
                         catalog_->ReadLedgerPage(row.id, request.camera_id(), request.lost_only(), offset, size));
  v1::LedgerPage page;
  page.set_take_id(row.id);
  page.set_total(rows.total);
  for (const storage::LedgerEntry& e : rows.entries) {
    v1::LedgerEntry* out = page.add_entries();
    out->set_camera_id(e.camera_id);
    out->set_slot(e.slot);
    out->set_pattern(e.pattern);
    out->set_reason(storage::ToProto(e.reason));
    if (e.frame_id) out->set_frame_id(*e.frame_id);
    out->set_detail(e.detail);
  }
  if (offset + static_cast<int64_t>(rows.entries.size()) < rows.total) {
    page.set_next_page_token(absl::StrCat(offset + static_cast<int64_t>(rows.entries.size())));
  }
  return page;
}

// The take's last processing graph run, from <take>/processing/status.json (written by its executors): nothing when
// there is none, or it cannot be read (logged; the catalog still lists the take).
void TakeRecords::AddGraphStatus(const std::string& take_dir, v1::TakeRecord* t) {
  const std::string path = take_dir + "/processing/status.json";
  std::error_code ec;
  if (!fs::exists(path, ec)) return;
  auto text = ReadFileToString(path, "processing status");
  const nlohmann::json j = text.ok() ? nlohmann::json::parse(*text, nullptr, false) : nlohmann::json();
  if (!j.is_object() || !j.contains("stages") || !j["stages"].is_array()) {
    Logger("controller")->warn("{}: not a processing status; the take's catalog entry goes without it", path);
    return;
  }
  static const std::map<std::string, v1::StageProcessingState> kStates = {
      {"done", v1::STAGE_PROCESSING_STATE_DONE},           {"running", v1::STAGE_PROCESSING_STATE_RUNNING},
      {"pending", v1::STAGE_PROCESSING_STATE_PENDING},     {"failed", v1::STAGE_PROCESSING_STATE_FAILED},
      {"cancelled", v1::STAGE_PROCESSING_STATE_CANCELLED}, {"incomplete", v1::STAGE_PROCESSING_STATE_INCOMPLETE}};
  for (const auto& s : j["stages"]) {
    v1::StageProcessing* p = t->add_processing();
    p->set_stage(ParseProcessingStage(s.value("stage", "")).value_or(v1::PROCESSING_STAGE_UNSPECIFIED));
    const auto state = kStates.find(s.value("state", ""));
    p->set_state(state == kStates.end() ? v1::STAGE_PROCESSING_STATE_UNSPECIFIED : state->second);
    p->set_units(s.value("units", int64_t{0}));
    p->set_up_to_date(s.value("up_to_date", int64_t{0}));
  }
}

absl::StatusOr<v1::TakeList> TakeRecords::ListTakes() const {
  STAGE_ASSIGN_OR_RETURN(std::vector<storage::TakeRow> rows, catalog_->ListTakes());
  v1::TakeList list;
  list.set_take_root(take_root_);
  for (const auto& r : rows) {
    v1::TakeRecord* t = list.add_takes();
    t->set_id(r.id);
    t->set_name(r.name);
    t->set_state(r.state);
    t->set_outcome(r.outcome);
    t->set_created_unix_ns(r.created_unix_ns);
    t->set_duration_s(r.duration_s);
    t->set_size_bytes(static_cast<uint64_t>(r.size_bytes));
    t->set_frames_expected(r.frames_expected);
    t->set_frames_stored(r.frames_stored);
    t->set_dir((fs::path(take_root_) / r.dir).string());
    std::error_code ec;
    std::vector<std::string> stages;
    for (const auto& entry : fs::directory_iterator(fs::path(t->dir()) / "derived", ec)) {
      if (entry.is_directory(ec)) stages.push_back(entry.path().filename().string());
    }
    std::sort(stages.begin(), stages.end());
    for (std::string& stage : stages) t->add_processed(std::move(stage));
    AddGraphStatus(t->dir(), t);
  }
  return list;
}

absl::StatusOr<v1::TakeSummary> TakeRecords::GetTake(const std::string& id) const {
  STAGE_ASSIGN_OR_RETURN(const storage::TakeRow row, Row(id));
  const std::string path = (fs::path(take_root_) / row.dir / "take.json").string();
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path));
  nlohmann::json take = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (take.is_discarded() || !take.contains("summary")) {
    return absl::DataLossError(absl::StrCat(path, ": not a take file with a summary"));
  }
  v1::TakeSummary summary;
  if (absl::Status s = FromContractJson(take["summary"].dump(), &summary); !s.ok()) {
    return absl::DataLossError(absl::StrCat(path, ": ", s.message()));
  }
  return summary;
}

}  // namespace stage::controller
