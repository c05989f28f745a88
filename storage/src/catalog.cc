// The take catalog and ledger in SQLite: see catalog.h.
#include "stage/storage/catalog.h"

#include <sqlite3.h>

#include <algorithm>
#include <ctime>
#include <filesystem>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/status.h"
#include "stage/common/take_names.h"

namespace stage::storage {
namespace {

constexpr int kSchemaVersion = 1;
constexpr const char* kSchema = R"sql(
CREATE TABLE IF NOT EXISTS takes (
  id TEXT PRIMARY KEY,
  name TEXT NOT NULL DEFAULT '',
  state TEXT NOT NULL,
  created_unix_ns INTEGER NOT NULL,
  t0_unix_ns INTEGER NOT NULL DEFAULT 0,
  slots INTEGER NOT NULL DEFAULT 0,
  duration_s REAL NOT NULL DEFAULT 0,
  size_bytes INTEGER NOT NULL DEFAULT 0,
  frames_expected INTEGER NOT NULL DEFAULT 0,
  frames_stored INTEGER NOT NULL DEFAULT 0,
  outcome TEXT NOT NULL DEFAULT '',
  rig_hash TEXT NOT NULL DEFAULT '',
  schedule_hash TEXT NOT NULL DEFAULT '',
  dir TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS ledger (
  take_id TEXT NOT NULL REFERENCES takes(id),
  camera_id TEXT NOT NULL,
  slot INTEGER NOT NULL,
  pattern INTEGER NOT NULL,
  reason INTEGER NOT NULL,
  frame_id INTEGER,
  detail TEXT NOT NULL DEFAULT '',
  PRIMARY KEY (take_id, camera_id, slot)
) WITHOUT ROWID;
)sql";

constexpr const char* kTakeColumns =
    "id, name, state, created_unix_ns, t0_unix_ns, slots, duration_s, size_bytes, frames_expected, frames_stored, "
    "outcome, rig_hash, schedule_hash, dir";

// A prepared statement, finalized on scope exit.
class Statement {
 public:
  Statement(sqlite3* db, const char* sql) { rc_ = sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr); }
  ~Statement() { sqlite3_finalize(stmt_); }
  Statement(const Statement&) = delete;
  Statement& operator=(const Statement&) = delete;
  bool ok() const { return rc_ == SQLITE_OK; }
  sqlite3_stmt* get() const { return stmt_; }
  void Bind(int i, const std::string& v) {
    sqlite3_bind_text(stmt_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT);
  }
  void Bind(int i, int64_t v) { sqlite3_bind_int64(stmt_, i, v); }
  void Bind(int i, double v) { sqlite3_bind_double(stmt_, i, v); }
  std::string Text(int i) const {
    const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(stmt_, i));
    return p == nullptr ? std::string() : std::string(p, static_cast<size_t>(sqlite3_column_bytes(stmt_, i)));
  }
  int64_t Int(int i) const { return sqlite3_column_int64(stmt_, i); }
  double Real(int i) const { return sqlite3_column_double(stmt_, i); }
  bool Null(int i) const { return sqlite3_column_type(stmt_, i) == SQLITE_NULL; }

 private:
  sqlite3_stmt* stmt_ = nullptr;
  int rc_ = SQLITE_ERROR;
};

void BindTake(Statement& s, const TakeRow& t) {
  s.Bind(1, t.id);
  s.Bind(2, t.name);
  s.Bind(3, TakeStateText(t.state));
  s.Bind(4, t.created_unix_ns);
  s.Bind(5, t.t0_unix_ns);
  s.Bind(6, t.slots);
  s.Bind(7, t.duration_s);
  s.Bind(8, t.size_bytes);
  s.Bind(9, t.frames_expected);
  s.Bind(10, t.frames_stored);
  s.Bind(11, TakeOutcomeText(t.outcome));
  s.Bind(12, t.rig_hash);
  s.Bind(13, t.schedule_hash);
  s.Bind(14, t.dir);
}

absl::StatusOr<TakeRow> ReadTake(const Statement& s, const std::string& path) {
  TakeRow t;
  t.id = s.Text(0);
  t.name = s.Text(1);
  auto state = TakeStateFromText(s.Text(2));
  auto outcome = TakeOutcomeFromText(s.Text(10));
  for (const absl::Status& bad : {state.status(), outcome.status()}) {
    if (!bad.ok()) return absl::DataLossError(absl::StrCat(path, ": take ", t.id, ": ", bad.message()));
  }
  t.state = *state;
  t.outcome = *outcome;
  t.created_unix_ns = s.Int(3);
  t.t0_unix_ns = s.Int(4);
  t.slots = s.Int(5);
  t.duration_s = s.Real(6);
  t.size_bytes = s.Int(7);
  t.frames_expected = s.Int(8);
  t.frames_stored = s.Int(9);
  t.rig_hash = s.Text(11);
  t.schedule_hash = s.Text(12);
  t.dir = s.Text(13);
  return t;
}

void Count(LedgerCounts* c, const LedgerEntry& e) {
  ++c->expected;
  if (e.stored()) ++c->stored;
  if (e.reason != LossReason::kNone) ++c->lost[e.reason];
}

}  // namespace

std::string TakeStateText(v1::TakeState state) { return TakeStateName(state); }

std::string TakeOutcomeText(v1::TakeOutcome outcome) { return TakeOutcomeName(outcome); }

absl::StatusOr<v1::TakeState> TakeStateFromText(const std::string& text) {
  v1::TakeState state;
  if (text.empty() || !v1::TakeState_Parse(absl::StrCat("TAKE_STATE_", absl::AsciiStrToUpper(text)), &state)) {
    return absl::InvalidArgumentError(absl::StrCat("state \"", text, "\" is none of take.proto's TakeState"));
  }
  return state;
}

absl::StatusOr<v1::TakeOutcome> TakeOutcomeFromText(const std::string& text) {
  if (text.empty()) return v1::TAKE_OUTCOME_UNSPECIFIED;
  v1::TakeOutcome outcome;
  if (!v1::TakeOutcome_Parse(absl::StrCat("TAKE_OUTCOME_", text), &outcome)) {
    return absl::InvalidArgumentError(absl::StrCat("outcome \"", text, "\" is none of take.proto's TakeOutcome"));
  }
  return outcome;
}

std::string LossReasonName(LossReason reason) { return stage::LossReasonName(ToProto(reason)); }

absl::StatusOr<std::unique_ptr<Catalog>> Catalog::Open(const std::string& root) {
  std::error_code ec;
  std::filesystem::create_directories(root, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(root, ": cannot create the take root: ", ec.message()));
  std::unique_ptr<Catalog> c(new Catalog());
  c->path_ = (std::filesystem::path(root) / "catalog.sqlite").string();
  if (sqlite3_open_v2(c->path_.c_str(), &c->db_, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX,
                      nullptr) != SQLITE_OK) {
    return c->Error("cannot open the catalog");
  }
  sqlite3_busy_timeout(c->db_, 5000);
  int64_t found = 0;
  {
    Statement version(c->db_, "PRAGMA user_version");
    if (!version.ok() || sqlite3_step(version.get()) != SQLITE_ROW) return c->Error("is not an SQLite database");
    found = version.Int(0);
  }  // finalized: no read transaction stays open
  if (found > kSchemaVersion) {
    return absl::FailedPreconditionError(
        absl::StrCat(c->path_, ": catalog schema ", found, " is newer than this program's (", kSchemaVersion, ")"));
  }
  // WAL: readers never block the writer; synchronous FULL: a committed ledger survives a power cut.
  if (auto s = c->Exec("PRAGMA journal_mode=WAL; PRAGMA synchronous=FULL; PRAGMA foreign_keys=ON;"); !s.ok()) return s;
  if (auto s = c->Exec(kSchema); !s.ok()) return s;
  if (auto s = c->Exec(absl::StrCat("PRAGMA user_version=", kSchemaVersion).c_str()); !s.ok()) return s;
  return c;
}

Catalog::~Catalog() { sqlite3_close_v2(db_); }

absl::Status Catalog::Exec(const char* sql) const {
  char* message = nullptr;
  if (sqlite3_exec(db_, sql, nullptr, nullptr, &message) != SQLITE_OK) {
    std::string m = message != nullptr ? message : sqlite3_errmsg(db_);
    sqlite3_free(message);
    return absl::UnavailableError(absl::StrCat(path_, ": ", m));
  }
  return absl::OkStatus();
}

absl::Status Catalog::Error(const std::string& what) const {
  return absl::UnavailableError(absl::StrCat(path_, ": ", what, " (", db_ != nullptr ? sqlite3_errmsg(db_) : "", ")"));
}

absl::Status Catalog::CreateTake(const TakeRow& take) {
  if (take.id.empty()) return absl::InvalidArgumentError("a take needs an id");
  Statement s(db_, absl::StrCat("INSERT INTO takes (", kTakeColumns, ") VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)").c_str());
  if (!s.ok()) return Error("cannot prepare the insert");
  BindTake(s, take);
  const int rc = sqlite3_step(s.get());
  if (rc == SQLITE_CONSTRAINT) return absl::AlreadyExistsError(absl::StrCat("take \"", take.id, "\" exists"));
  if (rc != SQLITE_DONE) return Error(absl::StrCat("cannot record take ", take.id));
  return absl::OkStatus();
}

absl::Status Catalog::UpdateTake(const TakeRow& take) {
  Statement s(db_,
              "UPDATE takes SET name=?2, state=?3, created_unix_ns=?4, t0_unix_ns=?5, slots=?6, duration_s=?7, "
              "size_bytes=?8, frames_expected=?9, frames_stored=?10, outcome=?11, rig_hash=?12, schedule_hash=?13, "
              "dir=?14 WHERE id=?1");
  if (!s.ok()) return Error("cannot prepare the update");
  BindTake(s, take);
  if (sqlite3_step(s.get()) != SQLITE_DONE) return Error(absl::StrCat("cannot update take ", take.id));
  if (sqlite3_changes(db_) == 0) return absl::NotFoundError(absl::StrCat("no take \"", take.id, "\""));
  return absl::OkStatus();
}

absl::StatusOr<TakeRow> Catalog::GetTake(const std::string& id) const {
  Statement s(db_, absl::StrCat("SELECT ", kTakeColumns, " FROM takes WHERE id=?").c_str());
  if (!s.ok()) return Error("cannot prepare the query");
  s.Bind(1, id);
  const int rc = sqlite3_step(s.get());
  if (rc == SQLITE_DONE) return absl::NotFoundError(absl::StrCat("no take \"", id, "\" in ", path_));
  if (rc != SQLITE_ROW) return Error(absl::StrCat("cannot read take ", id));
  return ReadTake(s, path_);
}

absl::StatusOr<std::vector<TakeRow>> Catalog::ListTakes() const {
  Statement s(db_, absl::StrCat("SELECT ", kTakeColumns, " FROM takes ORDER BY created_unix_ns, id").c_str());
  if (!s.ok()) return Error("cannot prepare the query");
  std::vector<TakeRow> out;
  int rc;
  while ((rc = sqlite3_step(s.get())) == SQLITE_ROW) {
    absl::StatusOr<TakeRow> take = ReadTake(s, path_);
    if (!take.ok()) return take.status();
    out.push_back(*std::move(take));
  }
  if (rc != SQLITE_DONE) return Error("cannot list the takes");
  return out;
}

absl::StatusOr<std::string> Catalog::NextTakeId(const std::string& stage_id, int64_t unix_ns) const {
  const time_t seconds = static_cast<time_t>(unix_ns / 1'000'000'000);
  std::tm local{};
  localtime_r(&seconds, &local);
  const std::string prefix =
      absl::StrFormat("%s-%04d%02d%02d-", stage_id, local.tm_year + 1900, local.tm_mon + 1, local.tm_mday);
  Statement s(db_, "SELECT id FROM takes WHERE substr(id, 1, ?2) = ?1");
  if (!s.ok()) return Error("cannot prepare the query");
  s.Bind(1, prefix);
  s.Bind(2, static_cast<int64_t>(prefix.size()));
  int64_t next = 1;
  int rc;
  while ((rc = sqlite3_step(s.get())) == SQLITE_ROW) {
    const std::string id = s.Text(0);
    int64_t n = 0;
    if (absl::SimpleAtoi(id.substr(prefix.size()), &n)) next = std::max(next, n + 1);
  }
  if (rc != SQLITE_DONE) return Error("cannot read the take ids");
  return absl::StrFormat("%s%04d", prefix, next);
}

absl::Status Catalog::RecordLedger(const std::string& take_id, const std::vector<LedgerEntry>& entries) {
  if (auto s = Exec("BEGIN IMMEDIATE"); !s.ok()) return s;
  Statement s(db_,
              "INSERT OR REPLACE INTO ledger (take_id, camera_id, slot, pattern, reason, frame_id, detail) "
              "VALUES (?,?,?,?,?,?,?)");
  if (!s.ok()) {
    (void)Exec("ROLLBACK");
    return Error("cannot prepare the ledger insert");
  }
  for (const LedgerEntry& e : entries) {
    sqlite3_reset(s.get());
    s.Bind(1, take_id);
    s.Bind(2, e.camera_id);
    s.Bind(3, e.slot);
    s.Bind(4, static_cast<int64_t>(e.pattern));
    s.Bind(5, static_cast<int64_t>(e.reason));
    if (e.frame_id) {
      s.Bind(6, static_cast<int64_t>(*e.frame_id));
    } else {
      sqlite3_bind_null(s.get(), 6);
    }
    s.Bind(7, e.detail);
    if (sqlite3_step(s.get()) != SQLITE_DONE) {
      const absl::Status error = Error(
          absl::StrCat("cannot record the ledger of take ", take_id, " (camera ", e.camera_id, ", slot ", e.slot, ")"));
      (void)Exec("ROLLBACK");
      return error;
    }
  }
  return Exec("COMMIT");
}

absl::StatusOr<std::vector<LedgerEntry>> Catalog::Ledger(const std::string& take_id,
                                                         const std::string& camera_id) const {
  STAGE_ASSIGN_OR_RETURN(LedgerPage all, ReadLedgerPage(take_id, camera_id, false, 0, -1));
  return std::move(all.entries);
}

absl::StatusOr<Catalog::LedgerPage> Catalog::ReadLedgerPage(const std::string& take_id, const std::string& camera_id,
                                                            bool lost_only, int64_t offset, int64_t limit) const {
  // Lost: neither stored (0) nor paused (7).
  constexpr const char* kWhere = "WHERE take_id=?1 AND (?2 = '' OR camera_id=?2) AND (?3 = 0 OR reason NOT IN (0, 7))";
  LedgerPage page;
  {
    Statement count(db_, absl::StrCat("SELECT COUNT(*) FROM ledger ", kWhere).c_str());
    if (!count.ok()) return Error("cannot prepare the query");
    count.Bind(1, take_id);
    count.Bind(2, camera_id);
    count.Bind(3, static_cast<int64_t>(lost_only));
    if (sqlite3_step(count.get()) != SQLITE_ROW)
      return Error(absl::StrCat("cannot count the ledger of take ", take_id));
    page.total = count.Int(0);
  }
  Statement s(db_, absl::StrCat("SELECT camera_id, slot, pattern, reason, frame_id, detail FROM ledger ", kWhere,
                                " ORDER BY camera_id, slot LIMIT ?4 OFFSET ?5")
                       .c_str());
  if (!s.ok()) return Error("cannot prepare the query");
  s.Bind(1, take_id);
  s.Bind(2, camera_id);
  s.Bind(3, static_cast<int64_t>(lost_only));
  s.Bind(4, limit);
  s.Bind(5, offset);
  int rc;
  while ((rc = sqlite3_step(s.get())) == SQLITE_ROW) {
    LedgerEntry e;
    e.camera_id = s.Text(0);
    e.slot = s.Int(1);
    e.pattern = static_cast<int32_t>(s.Int(2));
    e.reason = static_cast<LossReason>(s.Int(3));
    if (!s.Null(4)) e.frame_id = static_cast<uint64_t>(s.Int(4));
    e.detail = s.Text(5);
    page.entries.push_back(std::move(e));
  }
  if (rc != SQLITE_DONE) return Error(absl::StrCat("cannot read the ledger of take ", take_id));
  return page;
}

absl::StatusOr<LedgerSummary> Catalog::Summarize(const std::string& take_id) const {
  absl::StatusOr<std::vector<LedgerEntry>> entries = Ledger(take_id);
  if (!entries.ok()) return entries.status();
  LedgerSummary summary;
  for (const LedgerEntry& e : *entries) {
    Count(&summary.total, e);
    Count(&summary.by_camera[e.camera_id], e);
    Count(&summary.by_pattern[e.pattern], e);
  }
  return summary;
}

}  // namespace stage::storage
