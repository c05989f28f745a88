// Executors of the processing graph (docs/processing.md#executors): one interface, two kinds. `local` runs the plan's
// tasks as `stage-process task` processes on this machine, a pool of them at a time; `slurm` submits them to a Slurm
// cluster as job arrays (one per stage, an element per chunk of frames) with dependencies between them, and watches
// them through squeue and the tasks' own status files (no accounting database needed). Either way a failed task runs
// again up to the plan's retries, then is reported with its log, and the tasks after it are cancelled.
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/graph.h"

namespace stage::processing {

// What a run reports as it goes: a line per task that starts, ends, fails or is retried.
using GraphEvents = std::function<void(const std::string& line)>;

class GraphExecutor {
 public:
  virtual ~GraphExecutor() = default;
  virtual absl::string_view name() const = 0;
  // Runs the plan's needed tasks (its plan.json written) until each is done, failed or cancelled. An error is the
  // executor's own (no scheduler, a take the cluster cannot read), not a task's: those are in their status files.
  // `cancelled` (may be empty) ends the run early: running tasks are stopped, the rest cancelled.
  virtual absl::Status Execute(const GraphPlan& plan, const GraphEvents& events,
                               const std::function<bool()>& cancelled) = 0;
};

// stage-process beside the running program (stage-process itself, or processing-worker): what tasks run.
std::string DefaultTaskProgram();

struct LocalExecutorOptions {
  // Tasks at a time (each a process using its stage's threads).
  int jobs = 1;
  // The program tasks run as `PROGRAM task ...`; empty: DefaultTaskProgram().
  std::string program;
  absl::Status Validate() const;
};
std::unique_ptr<GraphExecutor> MakeLocalExecutor(const LocalExecutorOptions& options);

struct SlurmStageResources {
  int cpus = 2;            // --cpus-per-task
  std::string memory;      // --mem (e.g. "4G"); empty: the partition's default
  std::string time_limit;  // --time (e.g. "1:00:00"); empty: the SlurmOptions' time_limit
};

struct SlurmOptions {
  std::string partition;                                // --partition; empty: the cluster's default
  std::string account;                                  // --account; empty: none
  std::string time_limit;                               // --time of every task; empty: the partition's default
  std::map<GraphStage, SlurmStageResources> resources;  // per stage; a stage not listed gets the defaults
  std::vector<std::string> sbatch_args;                 // further sbatch flags, given to every submission
  // The program tasks run as, on the compute nodes (the same path there); empty: DefaultTaskProgram().
  std::string program;
  // Where sbatch, squeue, scontrol and scancel are; empty: PATH.
  std::string bin_dir;
  // How often the queue is looked at, milliseconds.
  int poll_ms = 500;
  // The first tiny job (is the take readable on a compute node?) must end within this, seconds.
  int probe_timeout_s = 600;
  absl::Status Validate() const;
};
std::unique_ptr<GraphExecutor> MakeSlurmExecutor(const SlurmOptions& options);

// A task that failed or was cancelled, for the report.
struct TaskFailure {
  std::string task;  // "fit.0"
  TaskState state = TaskState::kFailed;
  std::string message;
  std::string log;
};

struct GraphReport {
  GraphPlan plan;
  std::string executor;
  bool nothing_to_do = false;  // every output asked for was up to date: no task ran
  std::vector<StageProgress> stages;
  std::vector<TaskFailure> failures;
  bool ok() const { return failures.empty(); }
};

// Plans the run (PlanGraph) and, unless everything is up to date, executes it; one run of a take at a time (a second
// gets FailedPrecondition naming the first's pid). The report's failures are the tasks'; an error is the run's own.
absl::StatusOr<GraphReport> RunGraph(const GraphOptions& options, GraphExecutor& executor, const GraphEvents& events,
                                     const std::function<bool()>& cancelled = {});

// The report as a table, and as JSON (stagectl and stage-process --json).
std::string FormatGraphReport(const GraphReport& report);
std::string GraphReportJson(const GraphReport& report);
// The plan as a table: per task, whether it runs and why (stage-process run --dry-run).
std::string FormatGraphPlan(const GraphPlan& plan);

}  // namespace stage::processing
