// The processing graph (docs/processing.md#the-graph): the stages of a take's processing, what each reads and writes
// (per frame, in frame order, or per take), the tasks that bring the outputs asked for up to date, and the manifests
// that say what made each output. The tasks run through an executor (graph_executor.h): this machine's pool or a
// Slurm cluster. A task is a `stage-process task` process; this file plans, and keeps the books around it.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace stage::processing {

// A stage of the graph (v1::ProcessingStage at the RPC edge). Declared in dependency order.
enum class GraphStage { kCalibration, kMvs, kPhotometric, kFit, kTextures, kStabilize };
inline constexpr GraphStage kGraphStages[] = {GraphStage::kCalibration, GraphStage::kMvs,      GraphStage::kPhotometric,
                                              GraphStage::kFit,         GraphStage::kTextures, GraphStage::kStabilize};

// How a stage's work divides into tasks, and its outputs into units (each with its manifest).
enum class Grain {
  kFrame,  // each frame on its own: chunks of frames are tasks, run in parallel; a unit is a frame's directory
  kTrack,  // frames in order, each starting from the one before (the template fit): one task; a unit is a frame's
           // directory, made from every frame before it
  kTake,   // the frames together (calibration, stabilization): one task, one unit (the stage's directory)
};

// What a stage needs of a stage before it, for its frame f.
enum class Need {
  kSameFrame,  // that stage's frame f
  kAllFrames,  // that stage's every frame of the run
};

struct StageInput {
  GraphStage stage;
  Need need;
};

struct StageSpec {
  GraphStage stage;
  absl::string_view name;    // the word in --stages, and the stage-process command that runs it
  absl::string_view output;  // its results: <take>/derived/<output>
  Grain grain;
  bool reads_recording;    // reads the take's frame files (cameras/*.h5): they are among its inputs
  bool takes_calibration;  // is given the run's --calibration (which is among its inputs)
  std::vector<StageInput> inputs;
};

const StageSpec& SpecOf(GraphStage stage);
absl::string_view GraphStageName(GraphStage stage);
// "mvs" -> kMvs; nullopt for a word that names no stage.
std::optional<GraphStage> ParseGraphStage(absl::string_view name);

struct GraphOptions {
  // The take directory (takes/<take-id>).
  std::string take_dir;
  // The outputs asked for; the stages they need are added. Empty: every stage but calibration (which runs on a take
  // of the board, and whose output the others read through `calibration`).
  std::vector<GraphStage> stages;
  // Virtual frames [first_frame, last_frame); last_frame < 0: every frame the take recorded.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // Frames per task of a per-frame stage (a Slurm array's element).
  int64_t chunk_frames = 4;
  // Where the cameras are, for the stages that place them: a calibration file or a directory holding cameras.json,
  // relative to the take or absolute. Empty: the rig's nominal models.
  std::string calibration;
  // Further stage-process flags per stage (e.g. {kMvs, {"--image-scale", "0.25"}}): part of each output's manifest,
  // so that changing one redoes that stage and what depends on it.
  std::map<GraphStage, std::vector<std::string>> stage_args;
  // A failed task runs again this many times before the run reports it.
  int retries = 1;

  absl::Status Validate() const;
};

// One task: a stage over frames [first, last).
struct GraphTask {
  GraphStage stage;
  int chunk = 0;  // its index among the stage's tasks (a Slurm array's task id)
  int64_t first = 0, last = 0;
  // Why it runs: "up to date" tasks are not run; the others are "missing", "stale: <what changed>", or "after <stage>"
  // (a stage before it runs, and may change its inputs: the task looks again when it starts).
  bool needed = false;
  std::string reason;
};

// What a run of the graph does: its tasks in dependency order, the stages' order, and where its books are.
struct GraphPlan {
  GraphOptions options;
  std::string take_dir;  // absolute
  int64_t first_frame = 0, last_frame = 0;
  std::vector<GraphStage> stages;  // the stages the run covers, in dependency order
  std::vector<GraphTask> tasks;    // by stage (in `stages` order), then chunk
  // The inputs from outside the graph, hashed once per run: the recording (take.json and its frame files' sizes) and
  // the calibration's file ("" for the nominal models).
  std::string recording_sha256, calibration_sha256;
  // <take>/processing: plan.json, status/<task>.json, logs/<task>.log, work/ (outputs before they are put in place)
  std::string run_dir;
  // This run's id (random, set when the plan is written): a task started for another run (a Slurm job an earlier,
  // killed run left queued) refuses to run against this one's plan.
  std::string run_id;

  // The tasks of `stage`, by chunk.
  std::vector<const GraphTask*> TasksOf(GraphStage stage) const;
  // Index of the task (stage, chunk) in `tasks`; -1 if none.
  int Find(GraphStage stage, int chunk) const;
  // The tasks `task` waits for (indices into `tasks`): for each of its stage's inputs in the run, the tasks that make
  // the frames it reads. Only needed tasks count.
  std::vector<int> DependenciesOf(int task) const;
  // True when every task of `task`'s stage needs exactly the same-numbered task of every stage it waits for, and no
  // other (Slurm's aftercorr).
  bool ChunkToChunk(GraphStage stage) const;
  // "mvs.2": the task's name in logs, status files and Slurm job names.
  std::string TaskName(const GraphTask& task) const;
  int needed_tasks() const;
};

// A take's processing directory (<take>/processing, absolute): a run's books.
std::string GraphRunDir(const std::string& take_dir);

// Plans a run: which tasks bring the outputs asked for up to date. Reads the manifests in place; writes nothing.
absl::StatusOr<GraphPlan> PlanGraph(const GraphOptions& options);

// plan.json in run_dir (written atomically), and read back by each task.
absl::Status WritePlan(const GraphPlan& plan);
absl::StatusOr<GraphPlan> ReadPlan(const std::string& run_dir);

// A task's state, in status/<task>.json: what the executors watch instead of the scheduler's accounting.
enum class TaskState { kPending, kRunning, kDone, kFailed, kCancelled };
absl::string_view TaskStateName(TaskState state);

struct TaskStatus {
  TaskState state = TaskState::kPending;
  int attempt = 0;
  int64_t pid = 0;
  std::string host;
  std::string log;      // the task's log file
  std::string message;  // why it failed; what it did ("3 frame(s) made, 1 up to date")
  int64_t made = 0, up_to_date = 0;
  // This attempt's wall time and CPU time (every thread of the task's process), seconds.
  double wall_s = 0, cpu_s = 0;
};
std::string StatusPath(const GraphPlan& plan, const GraphTask& task);
std::string LogPath(const GraphPlan& plan, const GraphTask& task);
absl::Status WriteTaskStatus(const std::string& path, const TaskStatus& status);
// NotFound when the task has written none yet.
absl::StatusOr<TaskStatus> ReadTaskStatus(const std::string& path);

// Runs one stage over frames into a directory, as `stage-process <name> --take T --frames A:B --output DIR
// [--calibration C] ARGS...` would: the executable's side of a task (stage-process passes its own commands).
using StageRunner = std::function<absl::Status(const std::vector<std::string>& argv)>;

// Runs task `index` of the plan (attempt `attempt`, counted from 1; `run_id`, when not empty, must be the plan's): for
// each unit of its frames, whether its manifest says it is up to date; if any is not, the stage runs over the task's
// frames into a work directory, each unit gets its manifest, and the units replace the old ones one rename each (a
// killed task leaves the old outputs or the new, never half of either). Writes the task's status file as it goes.
absl::Status RunGraphTask(const GraphPlan& plan, int index, int attempt, const StageRunner& run,
                          const std::string& run_id = "");

// Per stage of the run: its units, and how many are up to date now (stagectl takes and the console show this).
struct StageProgress {
  GraphStage stage;
  int64_t units = 0, up_to_date = 0;
  int tasks = 0, done = 0, failed = 0, cancelled = 0, running = 0;
};
// From the tasks' states as an executor holds them (indexed as plan.tasks; a task not needed counts up to date).
std::vector<StageProgress> GraphProgress(const GraphPlan& plan, const std::vector<TaskState>& states);
// From the tasks' status files (one read each: for a run's end, not for every task's).
std::vector<StageProgress> GraphProgress(const GraphPlan& plan);
// A stage's state in words: done, failed, cancelled, running, pending, or (once the run is over) incomplete.
std::string StageStateName(const StageProgress& p, bool finished);
// <take>/processing/status.json: the stages' progress, written by the executors as tasks start and end, read by the
// controller's take catalog, `stage-process status` and `run`'s progress lines.
absl::Status WriteGraphSummary(const GraphPlan& plan, const std::vector<StageProgress>& progress, bool finished);
// What WriteGraphSummary wrote; NotFound when no run has.
absl::StatusOr<std::vector<StageProgress>> ReadGraphSummary(const std::string& run_dir);

}  // namespace stage::processing
