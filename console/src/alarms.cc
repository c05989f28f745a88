#include "alarms.h"

#include <sqlite3.h>

#include <nlohmann/json.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "stage/v1/controller.pb.h"

namespace stage::console {
namespace {

constexpr const char* kSchema = R"sql(
CREATE TABLE IF NOT EXISTS alarms (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  key TEXT NOT NULL,
  kind TEXT NOT NULL,
  source TEXT NOT NULL,
  message TEXT NOT NULL,
  raised_unix_ns INTEGER NOT NULL,
  cleared_unix_ns INTEGER NOT NULL DEFAULT 0,
  acked_unix_ns INTEGER NOT NULL DEFAULT 0,
  acked_by TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS alarms_open ON alarms (cleared_unix_ns);
)sql";

absl::StatusOr<AlarmKind> ParseKind(absl::string_view name) {
  for (AlarmKind k : {AlarmKind::kNodeDown, AlarmKind::kEmergencyStop, AlarmKind::kLightFault, AlarmKind::kThermal,
                      AlarmKind::kLostFrames}) {
    if (AlarmKindName(k) == name) return k;
  }
  return absl::DataLossError(absl::StrCat("alarm kind '", name, "' unknown"));
}

std::string Text(sqlite3_stmt* s, int column) {
  const unsigned char* t = sqlite3_column_text(s, column);
  return t == nullptr ? std::string() : std::string(reinterpret_cast<const char*>(t));
}

bool ThermalFault(const std::string& fault) {
  const std::string f = absl::AsciiStrToLower(fault);
  return absl::StrContains(f, "temperature") || absl::StrContains(f, "thermal") || absl::StrContains(f, "hot");
}

}  // namespace

absl::string_view AlarmKindName(AlarmKind kind) {
  switch (kind) {
    case AlarmKind::kNodeDown:
      return "NODE_DOWN";
    case AlarmKind::kEmergencyStop:
      return "EMERGENCY_STOP";
    case AlarmKind::kLightFault:
      return "LIGHT_FAULT";
    case AlarmKind::kThermal:
      return "THERMAL";
    case AlarmKind::kLostFrames:
      return "LOST_FRAMES";
  }
  return "UNKNOWN";
}

std::string Alarm::ToJson() const {
  nlohmann::json j = {{"id", id},
                      {"key", key},
                      {"kind", std::string(AlarmKindName(kind))},
                      {"source", source},
                      {"message", message},
                      {"raised_unix_ms", raised_unix_ns / 1000000},
                      {"cleared_unix_ms", cleared_unix_ns / 1000000},
                      {"acked_unix_ms", acked_unix_ns / 1000000},
                      {"acked_by", acked_by},
                      {"active", active()}};
  return j.dump();
}

std::vector<AlarmCondition> ConditionsOf(const v1::StageStatus& status, const AlarmThresholds& thresholds) {
  std::vector<AlarmCondition> out;
  if (status.estop_latched()) {
    const std::string& why = status.estop_reason();
    out.push_back({"estop", AlarmKind::kEmergencyStop, "stage",
                   absl::StartsWith(why, "emergency stop") ? why : absl::StrCat("emergency stop: ", why)});
  }
  for (const v1::NodeStatus& n : status.nodes()) {
    if (n.state() == v1::NODE_STATE_DOWN || n.state() == v1::NODE_STATE_UNREACHABLE) {
      out.push_back(
          {absl::StrCat("node-down:", n.id()), AlarmKind::kNodeDown, n.id(),
           absl::StrCat(n.id(), " is ", n.state() == v1::NODE_STATE_DOWN ? "down" : "unreachable", ": ", n.reason())});
    }
  }
  for (const v1::NodeDevice& d : status.devices()) {
    if (d.has_light()) {
      const v1::LightStats& l = d.light();
      std::vector<std::string> thermal, other;
      for (const std::string& f : l.faults()) (ThermalFault(f) ? thermal : other).push_back(f);
      if (!other.empty()) {
        out.push_back({absl::StrCat("light-fault:", d.id()), AlarmKind::kLightFault, d.id(),
                       absl::StrCat(d.id(), " reports ", absl::StrJoin(other, "; "))});
      }
      if (!thermal.empty() || l.max_thermal_load() >= thresholds.thermal_load) {
        std::string why =
            thermal.empty() ? absl::StrFormat("the armed table reaches %.2f of the thermal limit", l.max_thermal_load())
                            : absl::StrJoin(thermal, "; ");
        if (l.temperature_c() != 0) absl::StrAppendFormat(&why, " (board at %.1f C)", l.temperature_c());
        out.push_back({absl::StrCat("thermal:", d.id()), AlarmKind::kThermal, d.id(), absl::StrCat(d.id(), ": ", why)});
      }
    }
    if (d.has_camera() && d.camera().take_frames_lost() > 0 && !d.camera().take_id().empty()) {
      const v1::CameraStats& c = d.camera();
      out.push_back({absl::StrCat("lost-frames:", d.id(), ":", c.take_id()), AlarmKind::kLostFrames, d.id(),
                     absl::StrCat(d.id(), " lost ", c.take_frames_lost(), " of ", c.take_frames_expected(),
                                  " frames of take ", c.take_id())});
    }
  }
  return out;
}

absl::StatusOr<std::unique_ptr<AlarmBook>> AlarmBook::Open(const std::string& path) {
  sqlite3* db = nullptr;
  if (sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX, nullptr) !=
      SQLITE_OK) {
    std::string why = db != nullptr ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::UnavailableError(absl::StrCat("alarm database ", path, ": ", why));
  }
  std::unique_ptr<AlarmBook> book(new AlarmBook(db));
  sqlite3_busy_timeout(db, 2000);
  for (const char* pragma : {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=NORMAL"}) {
    if (auto s = book->Exec(pragma); !s.ok())
      return absl::UnavailableError(absl::StrCat("alarm database ", path, ": ", s.message()));
  }
  if (auto s = book->Exec(kSchema); !s.ok()) {
    return absl::UnavailableError(absl::StrCat("alarm database ", path, ": ", s.message()));
  }
  auto open = book->Query("cleared_unix_ns = 0", 100000);
  if (!open.ok()) return absl::DataLossError(absl::StrCat("alarm database ", path, ": ", open.status().message()));
  for (Alarm& a : *open) book->active_[a.key] = std::move(a);
  return book;
}

AlarmBook::~AlarmBook() { sqlite3_close(db_); }

absl::Status AlarmBook::Exec(const std::string& sql) const {
  char* error = nullptr;
  if (sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error) != SQLITE_OK) {
    std::string why = error != nullptr ? error : "failed";
    sqlite3_free(error);
    return absl::InternalError(why);
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<Alarm>> AlarmBook::Query(const std::string& where, int limit) const {
  const std::string sql = absl::StrCat(
      "SELECT id, key, kind, source, message, raised_unix_ns, cleared_unix_ns, acked_unix_ns, acked_by FROM alarms",
      where.empty() ? "" : " WHERE ", where, " ORDER BY id DESC LIMIT ", limit);
  sqlite3_stmt* s = nullptr;
  if (sqlite3_prepare_v2(db_, sql.c_str(), -1, &s, nullptr) != SQLITE_OK)
    return absl::InternalError(sqlite3_errmsg(db_));
  std::vector<Alarm> out;
  int rc;
  while ((rc = sqlite3_step(s)) == SQLITE_ROW) {
    Alarm a;
    a.id = sqlite3_column_int64(s, 0);
    a.key = Text(s, 1);
    auto kind = ParseKind(Text(s, 2));
    if (!kind.ok()) {
      sqlite3_finalize(s);
      return kind.status();
    }
    a.kind = *kind;
    a.source = Text(s, 3);
    a.message = Text(s, 4);
    a.raised_unix_ns = sqlite3_column_int64(s, 5);
    a.cleared_unix_ns = sqlite3_column_int64(s, 6);
    a.acked_unix_ns = sqlite3_column_int64(s, 7);
    a.acked_by = Text(s, 8);
    out.push_back(std::move(a));
  }
  sqlite3_finalize(s);
  if (rc != SQLITE_DONE) return absl::InternalError(sqlite3_errmsg(db_));
  return out;
}

absl::Status AlarmBook::Insert(Alarm* a) {
  sqlite3_stmt* s = nullptr;
  if (sqlite3_prepare_v2(db_, "INSERT INTO alarms (key, kind, source, message, raised_unix_ns) VALUES (?, ?, ?, ?, ?)",
                         -1, &s, nullptr) != SQLITE_OK) {
    return absl::InternalError(sqlite3_errmsg(db_));
  }
  const std::string kind(AlarmKindName(a->kind));
  sqlite3_bind_text(s, 1, a->key.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_text(s, 2, kind.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_text(s, 3, a->source.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_text(s, 4, a->message.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int64(s, 5, a->raised_unix_ns);
  const int rc = sqlite3_step(s);
  sqlite3_finalize(s);
  if (rc != SQLITE_DONE) return absl::InternalError(sqlite3_errmsg(db_));
  a->id = sqlite3_last_insert_rowid(db_);
  return absl::OkStatus();
}

absl::Status AlarmBook::Save(const Alarm& a) {
  sqlite3_stmt* s = nullptr;
  if (sqlite3_prepare_v2(
          db_, "UPDATE alarms SET message = ?, cleared_unix_ns = ?, acked_unix_ns = ?, acked_by = ? WHERE id = ?", -1,
          &s, nullptr) != SQLITE_OK) {
    return absl::InternalError(sqlite3_errmsg(db_));
  }
  sqlite3_bind_text(s, 1, a.message.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int64(s, 2, a.cleared_unix_ns);
  sqlite3_bind_int64(s, 3, a.acked_unix_ns);
  sqlite3_bind_text(s, 4, a.acked_by.c_str(), -1, SQLITE_TRANSIENT);
  sqlite3_bind_int64(s, 5, a.id);
  const int rc = sqlite3_step(s);
  sqlite3_finalize(s);
  if (rc != SQLITE_DONE) return absl::InternalError(sqlite3_errmsg(db_));
  return absl::OkStatus();
}

absl::StatusOr<std::vector<Alarm>> AlarmBook::Update(const std::vector<AlarmCondition>& conditions,
                                                     int64_t now_unix_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<Alarm> changed;
  std::map<std::string, const AlarmCondition*> now;
  for (const AlarmCondition& c : conditions) now[c.key] = &c;
  for (auto it = active_.begin(); it != active_.end();) {
    if (now.count(it->first) != 0) {
      ++it;
      continue;
    }
    it->second.cleared_unix_ns = now_unix_ns;
    if (auto s = Save(it->second); !s.ok()) return s;
    changed.push_back(it->second);
    it = active_.erase(it);
  }
  for (const auto& [key, c] : now) {
    auto it = active_.find(key);
    if (it == active_.end()) {
      Alarm a;
      a.key = key;
      a.kind = c->kind;
      a.source = c->source;
      a.message = c->message;
      a.raised_unix_ns = now_unix_ns;
      if (auto s = Insert(&a); !s.ok()) return s;
      changed.push_back(a);
      active_[key] = std::move(a);
    } else if (it->second.message != c->message) {
      it->second.message = c->message;
      if (auto s = Save(it->second); !s.ok()) return s;
      changed.push_back(it->second);
    }
  }
  return changed;
}

absl::StatusOr<Alarm> AlarmBook::Acknowledge(int64_t id, const std::string& user, int64_t now_unix_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  // An active alarm, or one of the history.
  Alarm* active = nullptr;
  for (auto& [key, a] : active_) {
    if (a.id == id) active = &a;
  }
  Alarm alarm;
  if (active != nullptr) {
    alarm = *active;
  } else {
    auto rows = Query(absl::StrCat("id = ", id), 1);
    if (!rows.ok()) return rows.status();
    if (rows->empty()) return absl::NotFoundError(absl::StrCat("no alarm ", id));
    alarm = rows->front();
  }
  if (alarm.acked_unix_ns == 0) {
    alarm.acked_unix_ns = now_unix_ns;
    alarm.acked_by = user;
    if (auto s = Save(alarm); !s.ok()) return s;
    if (active != nullptr) *active = alarm;
  }
  return alarm;
}

std::vector<Alarm> AlarmBook::Active() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<Alarm> out;
  for (const auto& [key, a] : active_) out.push_back(a);
  std::sort(out.begin(), out.end(), [](const Alarm& a, const Alarm& b) { return a.id > b.id; });
  return out;
}

absl::StatusOr<std::vector<Alarm>> AlarmBook::History(int limit) const {
  std::lock_guard<std::mutex> lock(mutex_);
  return Query("", limit);
}

}  // namespace stage::console
