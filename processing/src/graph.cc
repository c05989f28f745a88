// The processing graph's stages, plans and task bookkeeping (graph.h). Manifests and hashes: graph_manifest.cc.
#include "stage/processing/graph.h"

#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "graph_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"

namespace stage::processing {
namespace fs = std::filesystem;

namespace {

const std::vector<StageSpec>& Specs() {
  static const std::vector<StageSpec> specs = {
      {GraphStage::kCalibration, "calibrate", "calibration", Grain::kTake, true, false, {}},
      {GraphStage::kMvs, "mvs", "mvs", Grain::kFrame, true, true, {}},
      {GraphStage::kPhotometric,
       "photometric",
       "photometric",
       Grain::kFrame,
       true,
       true,
       {{GraphStage::kMvs, Need::kSameFrame}}},
      {GraphStage::kFit, "fit", "fit", Grain::kTrack, false, false, {{GraphStage::kMvs, Need::kAllFrames}}},
      {GraphStage::kTextures,
       "textures",
       "textures",
       Grain::kFrame,
       false,
       true,
       {{GraphStage::kFit, Need::kSameFrame}, {GraphStage::kPhotometric, Need::kSameFrame}}},
      {GraphStage::kStabilize,
       "stabilize",
       "textures-stable",
       Grain::kTake,
       false,
       false,
       {{GraphStage::kTextures, Need::kAllFrames}}},
  };
  return specs;
}

}  // namespace

const StageSpec& SpecOf(GraphStage stage) { return Specs()[static_cast<size_t>(stage)]; }
absl::string_view GraphStageName(GraphStage stage) { return SpecOf(stage).name; }

std::optional<GraphStage> ParseGraphStage(absl::string_view name) {
  for (const StageSpec& s : Specs()) {
    if (s.name == name) return s.stage;
  }
  if (name == "calibration") return GraphStage::kCalibration;
  return std::nullopt;
}

absl::string_view TaskStateName(TaskState state) {
  switch (state) {
    case TaskState::kPending:
      return "pending";
    case TaskState::kRunning:
      return "running";
    case TaskState::kDone:
      return "done";
    case TaskState::kFailed:
      return "failed";
    case TaskState::kCancelled:
      return "cancelled";
  }
  return "unknown";
}

absl::Status GraphOptions::Validate() const {
  if (take_dir.empty()) return absl::InvalidArgumentError("processing graph: no take directory");
  if (first_frame < 0 || (last_frame >= 0 && last_frame <= first_frame)) {
    return absl::InvalidArgumentError(
        absl::StrCat("processing graph: frames [", first_frame, ", ", last_frame, ") are empty"));
  }
  if (chunk_frames < 1) {
    return absl::InvalidArgumentError(absl::StrCat("processing graph: chunk_frames ", chunk_frames, " is not >= 1"));
  }
  if (retries < 0 || retries > 100) {
    return absl::InvalidArgumentError(absl::StrCat("processing graph: retries ", retries, " is not in 0..100"));
  }
  for (const auto& [stage, args] : stage_args) {
    for (const std::string& a : args) {
      for (const char* reserved : {"--take", "--frames", "--output", "--calibration", "--json"}) {
        if (a == reserved || a.rfind(absl::StrCat(reserved, "="), 0) == 0) {
          return absl::InvalidArgumentError(
              absl::StrCat("processing graph: ", GraphStageName(stage), "'s option ", a, " is the graph's to set"));
        }
      }
    }
  }
  return absl::OkStatus();
}

std::vector<const GraphTask*> GraphPlan::TasksOf(GraphStage stage) const {
  std::vector<const GraphTask*> out;
  for (const GraphTask& t : tasks) {
    if (t.stage == stage) out.push_back(&t);
  }
  return out;
}

int GraphPlan::Find(GraphStage stage, int chunk) const {
  for (size_t i = 0; i < tasks.size(); ++i) {
    if (tasks[i].stage == stage && tasks[i].chunk == chunk) return static_cast<int>(i);
  }
  return -1;
}

std::vector<int> GraphPlan::DependenciesOf(int task) const { return internal::Dependencies(*this, task, true); }

bool GraphPlan::ChunkToChunk(GraphStage stage) const {
  const StageSpec& spec = SpecOf(stage);
  if (spec.grain != Grain::kFrame) return false;
  bool any = false;
  for (const StageInput& in : spec.inputs) {
    if (std::find(stages.begin(), stages.end(), in.stage) == stages.end()) continue;
    if (in.need != Need::kSameFrame || SpecOf(in.stage).grain != Grain::kFrame) return false;
    any = true;
  }
  return any;
}

std::string GraphPlan::TaskName(const GraphTask& task) const {
  return absl::StrCat(GraphStageName(task.stage), ".", task.chunk);
}

int GraphPlan::needed_tasks() const {
  return static_cast<int>(std::count_if(tasks.begin(), tasks.end(), [](const GraphTask& t) { return t.needed; }));
}

namespace internal {

std::vector<int> Dependencies(const GraphPlan& plan, int task, bool needed_only) {
  const GraphTask& t = plan.tasks[task];
  std::vector<int> out;
  for (const StageInput& in : SpecOf(t.stage).inputs) {
    for (size_t i = 0; i < plan.tasks.size(); ++i) {
      const GraphTask& u = plan.tasks[i];
      if (u.stage != in.stage || (needed_only && !u.needed)) continue;
      const bool overlaps = u.first < t.last && t.first < u.last;
      if (in.need == Need::kAllFrames || overlaps) out.push_back(static_cast<int>(i));
    }
  }
  return out;
}

}  // namespace internal

namespace {

// The stages asked for and every stage they read, in dependency order.
std::vector<GraphStage> Closure(const std::vector<GraphStage>& asked) {
  std::vector<bool> in(std::size(kGraphStages), false);
  std::vector<GraphStage> todo = asked;
  if (todo.empty()) {
    for (GraphStage s : kGraphStages) {
      if (s != GraphStage::kCalibration) todo.push_back(s);
    }
  }
  while (!todo.empty()) {
    const GraphStage s = todo.back();
    todo.pop_back();
    if (in[static_cast<size_t>(s)]) continue;
    in[static_cast<size_t>(s)] = true;
    for (const StageInput& i : SpecOf(s).inputs) todo.push_back(i.stage);
  }
  std::vector<GraphStage> out;
  for (GraphStage s : kGraphStages) {
    if (in[static_cast<size_t>(s)]) out.push_back(s);
  }
  return out;
}

// Why `task` must run, or "" when its units' manifests match what the task would make them from.
std::string Staleness(const GraphPlan& plan, const GraphTask& task) {
  const std::vector<internal::Unit> units = internal::UnitsOf(plan, task);
  auto keys = internal::TaskUnitKeys(plan, task, units);
  if (!keys.ok()) return absl::StrCat("inputs not ready (", keys.status().message(), ")");
  for (size_t i = 0; i < units.size(); ++i) {
    const std::string why = internal::CompareManifest(plan, task, units[i], (*keys)[i]);
    if (!why.empty()) return why;
  }
  return "";
}

}  // namespace

std::string GraphRunDir(const std::string& take_dir) {
  std::error_code ec;
  fs::path take = fs::absolute(take_dir, ec).lexically_normal();
  if (!take.has_filename()) take = take.parent_path();  // "takes/t/" as "takes/t"
  return (take / "processing").string();
}

absl::StatusOr<GraphPlan> PlanGraph(const GraphOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  GraphPlan plan;
  plan.options = options;
  std::error_code ec;
  plan.take_dir = fs::absolute(options.take_dir, ec).lexically_normal().string();
  while (plan.take_dir.size() > 1 && plan.take_dir.back() == '/') plan.take_dir.pop_back();
  plan.options.take_dir = plan.take_dir;
  plan.run_dir = GraphRunDir(plan.take_dir);
  STAGE_ASSIGN_OR_RETURN(const int64_t frames, internal::TakeFrames(plan.take_dir));
  plan.first_frame = options.first_frame;
  plan.last_frame = options.last_frame < 0 ? frames : options.last_frame;
  if (plan.last_frame > frames || plan.first_frame >= plan.last_frame) {
    return absl::InvalidArgumentError(absl::StrCat(plan.take_dir, ": frames [", plan.first_frame, ", ", plan.last_frame,
                                                   ") are not all in the take (it holds ", frames, " frame(s))"));
  }
  plan.stages = Closure(options.stages);
  STAGE_ASSIGN_OR_RETURN(plan.recording_sha256, internal::RecordingSha256(plan.take_dir));
  if (!options.calibration.empty()) {
    const fs::path cal = fs::path(options.calibration).is_absolute() ? fs::path(options.calibration)
                                                                     : fs::path(plan.take_dir) / options.calibration;
    const fs::path file = fs::is_directory(cal) ? cal / "cameras.json" : cal;
    STAGE_ASSIGN_OR_RETURN(plan.calibration_sha256, internal::FileSha256(file.string()));
  }
  for (GraphStage s : plan.stages) {
    const Grain grain = SpecOf(s).grain;
    const int64_t step = grain == Grain::kFrame ? options.chunk_frames : plan.last_frame - plan.first_frame;
    int chunk = 0;
    for (int64_t f = plan.first_frame; f < plan.last_frame; f += step) {
      plan.tasks.push_back({s, chunk++, f, std::min(plan.last_frame, f + step)});
    }
  }
  // In dependency order: a task runs when one it reads runs (its inputs may change), or when its own units are stale.
  for (size_t i = 0; i < plan.tasks.size(); ++i) {
    GraphTask& t = plan.tasks[i];
    for (int d : internal::Dependencies(plan, static_cast<int>(i), false)) {
      if (plan.tasks[d].needed) {
        t.needed = true;
        t.reason = absl::StrCat("after ", GraphStageName(plan.tasks[d].stage));
        break;
      }
    }
    if (!t.needed) {
      t.reason = Staleness(plan, t);
      t.needed = !t.reason.empty();
      if (!t.needed) t.reason = "up to date";
    }
  }
  return plan;
}

std::string StatusPath(const GraphPlan& plan, const GraphTask& task) {
  return absl::StrCat(plan.run_dir, "/status/", plan.TaskName(task), ".json");
}

std::string LogPath(const GraphPlan& plan, const GraphTask& task) {
  return absl::StrCat(plan.run_dir, "/logs/", plan.TaskName(task), ".log");
}

absl::Status WriteTaskStatus(const std::string& path, const TaskStatus& status) {
  nlohmann::ordered_json j;
  j["state"] = TaskStateName(status.state);
  j["attempt"] = status.attempt;
  j["pid"] = status.pid;
  j["host"] = status.host;
  j["log"] = status.log;
  j["message"] = status.message;
  j["units_made"] = status.made;
  j["units_up_to_date"] = status.up_to_date;
  j["wall_s"] = status.wall_s;
  j["cpu_s"] = status.cpu_s;
  std::error_code ec;
  fs::create_directories(fs::path(path).parent_path(), ec);
  return WriteFileAtomically(path, j.dump(2) + "\n");
}

namespace internal {

absl::Status WriteCancelled(const GraphPlan& plan, const GraphTask& task, const std::string& why) {
  TaskStatus s;
  s.state = TaskState::kCancelled;
  s.message = why;
  s.log = LogPath(plan, task);
  return WriteTaskStatus(StatusPath(plan, task), s);
}

}  // namespace internal

absl::StatusOr<TaskStatus> ReadTaskStatus(const std::string& path) {
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, "task status"));
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.is_object()) return absl::DataLossError(absl::StrCat(path, ": not a task status"));
  TaskStatus s;
  const std::string state = j.value("state", "");
  bool known = false;
  for (TaskState st :
       {TaskState::kPending, TaskState::kRunning, TaskState::kDone, TaskState::kFailed, TaskState::kCancelled}) {
    if (TaskStateName(st) == state) {
      s.state = st;
      known = true;
    }
  }
  if (!known) return absl::DataLossError(absl::StrCat(path, ": unknown state \"", state, "\""));
  s.attempt = j.value("attempt", 0);
  s.pid = j.value("pid", int64_t{0});
  s.host = j.value("host", "");
  s.log = j.value("log", "");
  s.message = j.value("message", "");
  s.made = j.value("units_made", int64_t{0});
  s.up_to_date = j.value("units_up_to_date", int64_t{0});
  s.wall_s = j.value("wall_s", 0.0);
  s.cpu_s = j.value("cpu_s", 0.0);
  return s;
}

std::vector<StageProgress> GraphProgress(const GraphPlan& plan) {
  std::vector<TaskState> states(plan.tasks.size(), TaskState::kPending);
  for (size_t i = 0; i < plan.tasks.size(); ++i) {
    if (!plan.tasks[i].needed) continue;
    auto status = ReadTaskStatus(StatusPath(plan, plan.tasks[i]));
    if (status.ok()) states[i] = status->state;
  }
  return GraphProgress(plan, states);
}

std::vector<StageProgress> GraphProgress(const GraphPlan& plan, const std::vector<TaskState>& states) {
  std::vector<StageProgress> out;
  for (GraphStage s : plan.stages) {
    StageProgress p{s};
    for (size_t i = 0; i < plan.tasks.size(); ++i) {
      const GraphTask& t = plan.tasks[i];
      if (t.stage != s) continue;
      const int64_t units = SpecOf(s).grain == Grain::kTake ? 1 : t.last - t.first;
      p.units += units;
      if (!t.needed) {
        p.up_to_date += units;
        continue;
      }
      ++p.tasks;
      switch (states[i]) {
        case TaskState::kDone:
          ++p.done;
          p.up_to_date += units;
          break;
        case TaskState::kFailed:
          ++p.failed;
          break;
        case TaskState::kCancelled:
          ++p.cancelled;
          break;
        case TaskState::kRunning:
          ++p.running;
          break;
        case TaskState::kPending:
          break;
      }
    }
    out.push_back(p);
  }
  return out;
}

namespace internal {

nlohmann::ordered_json StageJson(const StageProgress& p, bool finished) {
  return {{"stage", GraphStageName(p.stage)},
          {"state", StageStateName(p, finished)},
          {"units", p.units},
          {"up_to_date", p.up_to_date},
          {"tasks", p.tasks},
          {"tasks_running", p.running},
          {"tasks_done", p.done},
          {"tasks_failed", p.failed},
          {"tasks_cancelled", p.cancelled}};
}

}  // namespace internal

std::string StageStateName(const StageProgress& p, bool finished) {
  if (p.failed > 0) return "failed";
  if (p.cancelled > 0) return "cancelled";
  if (p.up_to_date >= p.units) return "done";
  if (finished) return "incomplete";
  return p.running > 0 ? "running" : "pending";
}

absl::Status WriteGraphSummary(const GraphPlan& plan, const std::vector<StageProgress>& progress, bool finished) {
  nlohmann::ordered_json j;
  j["frames"] = {plan.first_frame, plan.last_frame};
  j["finished"] = finished;
  j["stages"] = nlohmann::json::array();
  for (const StageProgress& p : progress) j["stages"].push_back(internal::StageJson(p, finished));
  return WriteFileAtomically(plan.run_dir + "/status.json", j.dump(2) + "\n");
}

absl::StatusOr<std::vector<StageProgress>> ReadGraphSummary(const std::string& run_dir) {
  const std::string path = run_dir + "/status.json";
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, "processing status"));
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.contains("stages") || !j["stages"].is_array()) {
    return absl::DataLossError(absl::StrCat(path, ": not a processing status"));
  }
  std::vector<StageProgress> out;
  for (const auto& s : j["stages"]) {
    const auto stage = ParseGraphStage(s.value("stage", ""));
    if (!stage) return absl::DataLossError(absl::StrCat(path, ": unknown stage ", s.value("stage", "")));
    StageProgress p{*stage};
    p.units = s.value("units", int64_t{0});
    p.up_to_date = s.value("up_to_date", int64_t{0});
    p.tasks = s.value("tasks", 0);
    p.running = s.value("tasks_running", 0);
    p.done = s.value("tasks_done", 0);
    p.failed = s.value("tasks_failed", 0);
    p.cancelled = s.value("tasks_cancelled", 0);
    out.push_back(p);
  }
  return out;
}

}  // namespace stage::processing
