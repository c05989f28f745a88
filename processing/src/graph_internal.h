// The processing graph's insides, shared by graph.cc (plans), graph_manifest.cc (units, keys, manifests, tasks) and
// their tests.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/graph.h"

namespace stage::processing::internal {

// An output unit: a frame's directory of a per-frame or tracked stage (rel "frame-NNNNNN"), or a per-take stage's
// whole directory (rel "", frame -1). Each holds a manifest.json.
struct Unit {
  std::string rel;
  int64_t frame = -1;
};

std::vector<Unit> UnitsOf(const GraphPlan& plan, const GraphTask& task);
// <take>/derived/<output>[/<rel>].
std::string UnitDir(const GraphPlan& plan, GraphStage stage, const Unit& unit);

// What a unit is made from, as JSON (stage, software version, the stage's flags, its frames where others' matter, the
// hashes of the recording, the calibration and the units of other stages it reads); "key" is its SHA-256. NotFound
// when a unit it reads has no manifest yet.
struct UnitKey {
  std::string parts;  // ordered JSON text
  std::string key;    // hex SHA-256 of parts
};
absl::StatusOr<UnitKey> MakeUnitKey(const GraphPlan& plan, const GraphTask& task, const Unit& unit);
// The keys of `units` (a task's, from UnitsOf). A tracked or per-take task's units share one key (each is made from
// every frame the task reads): it is worked out once, not once per frame of a long take.
absl::StatusOr<std::vector<UnitKey>> TaskUnitKeys(const GraphPlan& plan, const GraphTask& task,
                                                  const std::vector<Unit>& units);

// "" when the unit's manifest holds `key` and its files are there with their sizes; otherwise why not ("missing",
// "stale: the mvs stage's flags changed", "outputs changed: mesh.obj").
std::string CompareManifest(const GraphPlan& plan, const GraphTask& task, const Unit& unit, const UnitKey& key);

// Writes <dir>/manifest.json for a unit made in `dir` (the work directory, before it is put in place): the key's
// parts, and every file's size and SHA-256.
absl::Status WriteManifest(const std::string& dir, const GraphTask& task, const Unit& unit, const UnitKey& key);

// The frames a take recorded (take.json's summary).
absl::StatusOr<int64_t> TakeFrames(const std::string& take_dir);
// Hex SHA-256 of a file's bytes, or of a directory's calibration (cameras.json); of a take's recording: take.json's
// bytes and each frame file's name and size (a recorded take does not change; hashing its frames would read them all).
absl::StatusOr<std::string> FileSha256(const std::string& path);
absl::StatusOr<std::string> RecordingSha256(const std::string& take_dir);
std::string Sha256Hex(const std::string& bytes);

// The tasks `task` reads from (indices into plan.tasks); with `needed_only`, those that run.
std::vector<int> Dependencies(const GraphPlan& plan, int task, bool needed_only);

// A stage's progress as status.json and the run's --json report carry it.
nlohmann::ordered_json StageJson(const StageProgress& p, bool finished);

// Writes `task`'s status file: cancelled (never run, or stopped) for `why`, its log named.
absl::Status WriteCancelled(const GraphPlan& plan, const GraphTask& task, const std::string& why);

}  // namespace stage::processing::internal
