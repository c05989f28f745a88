// The console's alarms: conditions read off each stage status (a node down, the emergency stop, a light node's fault
// or thermal load, a camera losing a take's frames), raised when they begin and cleared when they end, acknowledged by
// an operator. Every alarm and acknowledgement is a row of a SQLite file, so both survive a console restart, and the
// rows are the alarms' history.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

struct sqlite3;

namespace stage::v1 {
class StageStatus;
}

namespace stage::console {

enum class AlarmKind {
  kNodeDown,       // a node's link: down or unreachable
  kEmergencyStop,  // latched
  kLightFault,     // a light node's board reports faults
  kThermal,        // a light node's armed table near its thermal limit (or the board says it is hot)
  kLostFrames,     // a camera lost frames of the take being recorded
};

absl::string_view AlarmKindName(AlarmKind kind);

struct Alarm {
  int64_t id = 0;
  // What the alarm is of: one alarm is open per key ("node-down:mv-03").
  std::string key;
  AlarmKind kind = AlarmKind::kNodeDown;
  std::string source;  // the node, or "stage"
  std::string message;
  int64_t raised_unix_ns = 0;
  int64_t cleared_unix_ns = 0;  // 0: still active
  int64_t acked_unix_ns = 0;    // 0: not acknowledged
  std::string acked_by;

  bool active() const { return cleared_unix_ns == 0; }
  // One line of JSON, for the console's API and event stream.
  std::string ToJson() const;
};

// A condition that holds now.
struct AlarmCondition {
  std::string key;
  AlarmKind kind;
  std::string source;
  std::string message;
};

struct AlarmThresholds {
  // A light node's armed table at or above this thermal load (of its limit, 1) raises a thermal alarm.
  double thermal_load = 0.9;
};

// The conditions a stage status shows.
std::vector<AlarmCondition> ConditionsOf(const v1::StageStatus& status, const AlarmThresholds& thresholds);

class AlarmBook {
 public:
  // Opens (creating) the database file; the alarms left open in it are active again.
  static absl::StatusOr<std::unique_ptr<AlarmBook>> Open(const std::string& path);
  ~AlarmBook();

  // Raises an alarm for each condition that has none open, clears the open ones whose condition has ended, and updates
  // the message of the others. Returns the alarms that changed.
  absl::StatusOr<std::vector<Alarm>> Update(const std::vector<AlarmCondition>& conditions, int64_t now_unix_ns);

  // Acknowledges alarm `id` (NotFound when there is none; acknowledging twice keeps the first).
  absl::StatusOr<Alarm> Acknowledge(int64_t id, const std::string& user, int64_t now_unix_ns);

  // The active alarms, newest first, and the latest `limit` of all (the history).
  std::vector<Alarm> Active() const;
  absl::StatusOr<std::vector<Alarm>> History(int limit) const;

 private:
  explicit AlarmBook(sqlite3* db) : db_(db) {}
  absl::Status Exec(const std::string& sql) const;
  absl::StatusOr<std::vector<Alarm>> Query(const std::string& where, int limit) const;
  absl::Status Insert(Alarm* alarm);
  absl::Status Save(const Alarm& alarm);

  mutable std::mutex mutex_;
  sqlite3* db_;
  std::map<std::string, Alarm> active_;  // by key; guarded by mutex_
};

}  // namespace stage::console
