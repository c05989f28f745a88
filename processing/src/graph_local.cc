// The local executor (graph_executor.h): the plan's tasks as `stage-process task` processes on this machine, up to
// `jobs` at a time, each started once the tasks it reads are done.
#include <algorithm>
#include <thread>

#include "absl/strings/str_cat.h"
#include "graph_internal.h"
#include "stage/common/status.h"
#include "stage/common/subprocess.h"
#include "stage/processing/graph_executor.h"

namespace stage::processing {

absl::Status LocalExecutorOptions::Validate() const {
  if (jobs < 1 || jobs > 256) {
    return absl::InvalidArgumentError(absl::StrCat("local executor: jobs ", jobs, " is not in 1..256"));
  }
  return absl::OkStatus();
}

namespace {

// One Execute's books: each task's dependencies (worked out once), state, attempts and process.
struct LocalRun {
  explicit LocalRun(const GraphPlan& p)
      : plan(p), state(p.tasks.size(), TaskState::kPending), attempts(p.tasks.size(), 0), running(p.tasks.size()) {
    for (size_t i = 0; i < p.tasks.size(); ++i) deps.push_back(p.DependenciesOf(static_cast<int>(i)));
  }
  bool Finished(size_t i) const {
    return !plan.tasks[i].needed || state[i] == TaskState::kDone || state[i] == TaskState::kFailed ||
           state[i] == TaskState::kCancelled;
  }
  bool Ready(size_t i) const {
    return std::all_of(deps[i].begin(), deps[i].end(), [&](int d) { return state[d] == TaskState::kDone; });
  }
  // status.json from the states held here (no status file read).
  void Summarize() const { (void)WriteGraphSummary(plan, GraphProgress(plan, state), false); }
  // Every needed task still pending after `failed` (transitively) cancelled, here and in its status file; tasks come
  // after what they read, so one pass reaches them all.
  void CancelAfter(size_t failed, const GraphEvents& events) {
    for (size_t i = 0; i < plan.tasks.size(); ++i) {
      if (!plan.tasks[i].needed || state[i] != TaskState::kPending) continue;
      const bool after = std::any_of(deps[i].begin(), deps[i].end(), [&](int d) {
        return static_cast<size_t>(d) == failed || state[d] == TaskState::kCancelled;
      });
      if (!after) continue;
      state[i] = TaskState::kCancelled;
      const std::string why = absl::StrCat("not run: ", plan.TaskName(plan.tasks[failed]), " failed");
      (void)internal::WriteCancelled(plan, plan.tasks[i], why);
      if (events) events(absl::StrCat(plan.TaskName(plan.tasks[i]), " cancelled: ", why));
    }
  }

  const GraphPlan& plan;
  std::vector<std::vector<int>> deps;
  std::vector<TaskState> state;
  std::vector<int> attempts;
  std::vector<std::unique_ptr<Subprocess>> running;
};

class LocalExecutor final : public GraphExecutor {
 public:
  explicit LocalExecutor(LocalExecutorOptions options) : options_(std::move(options)) {
    if (options_.program.empty()) options_.program = DefaultTaskProgram();
  }
  absl::string_view name() const override { return "local"; }

  absl::Status Execute(const GraphPlan& plan, const GraphEvents& events,
                       const std::function<bool()>& cancelled) override {
    STAGE_RETURN_IF_ERROR(options_.Validate());
    LocalRun run(plan);
    const size_t n = plan.tasks.size();
    while (true) {
      size_t active = 0, open = 0;
      for (size_t i = 0; i < n; ++i) {
        if (run.running[i]) ReapIfEnded(&run, i, events);
      }
      if (cancelled && cancelled()) return StopAll(&run);
      for (size_t i = 0; i < n; ++i) {
        if (run.running[i]) ++active;
        if (!run.Finished(i)) ++open;
      }
      if (open == 0) return absl::OkStatus();
      for (size_t i = 0; i < n && active < static_cast<size_t>(options_.jobs); ++i) {
        if (run.state[i] != TaskState::kPending || !plan.tasks[i].needed || !run.Ready(i)) continue;
        STAGE_RETURN_IF_ERROR(Start(&run, i, events));
        ++active;
      }
      if (active == 0) return absl::InternalError("local executor: tasks wait for none running (a cycle?)");
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }

 private:
  absl::Status Start(LocalRun* run, size_t i, const GraphEvents& events) const {
    const GraphPlan& plan = run->plan;
    const int attempt = ++run->attempts[i];
    SubprocessOptions o;
    o.argv = {options_.program,        "task",     "--run-dir", plan.run_dir, "--task", std::to_string(i), "--attempt",
              std::to_string(attempt), "--run-id", plan.run_id};
    o.stdout_path = o.stderr_path = LogPath(plan, plan.tasks[i]);
    o.append = true;
    STAGE_ASSIGN_OR_RETURN(run->running[i], Subprocess::Spawn(o));
    run->state[i] = TaskState::kRunning;
    run->Summarize();
    if (events) {
      events(absl::StrCat(plan.TaskName(plan.tasks[i]), " started (frames ", plan.tasks[i].first, ":",
                          plan.tasks[i].last, ", attempt ", attempt, ", pid ", run->running[i]->pid(), ")"));
    }
    return absl::OkStatus();
  }

  // A task's process that has ended: done, run again, or failed (and what waits for it cancelled).
  void ReapIfEnded(LocalRun* run, size_t i, const GraphEvents& events) const {
    const GraphPlan& plan = run->plan;
    const std::optional<ExitInfo> exit = run->running[i]->Poll();
    if (!exit) return;
    run->running[i].reset();
    const std::string name = plan.TaskName(plan.tasks[i]);
    const std::string path = StatusPath(plan, plan.tasks[i]);
    auto status = ReadTaskStatus(path);
    const int attempts = run->attempts[i];
    if (exit->ok() && status.ok() && status->state == TaskState::kDone) {
      run->state[i] = TaskState::kDone;
      run->Summarize();  // before the news: `stage-process run` prints status.json's progress on it
      if (events) events(absl::StrCat(name, " done: ", status->message));
      return;
    }
    const std::string why = status.ok() && status->state == TaskState::kFailed ? status->message : exit->Describe();
    if (attempts <= plan.options.retries) {
      run->state[i] = TaskState::kPending;
      run->Summarize();
      if (events) events(absl::StrCat(name, " attempt ", attempts, " failed (", why, "): retrying"));
      return;
    }
    run->state[i] = TaskState::kFailed;
    if (!status.ok() || status->state != TaskState::kFailed) {
      TaskStatus s = status.ok() ? *status : TaskStatus{};
      s.state = TaskState::kFailed;
      s.attempt = attempts;
      s.message = why;
      s.log = LogPath(plan, plan.tasks[i]);
      (void)WriteTaskStatus(path, s);
    }
    run->CancelAfter(i, events);
    run->Summarize();
    if (events) events(absl::StrCat(name, " failed after ", attempts, " attempt(s): ", why));
  }

  static absl::Status StopAll(LocalRun* run) {
    for (size_t i = 0; i < run->running.size(); ++i) {
      if (run->running[i]) run->running[i]->Terminate(std::chrono::seconds(5));
      if (run->plan.tasks[i].needed && (run->state[i] == TaskState::kPending || run->state[i] == TaskState::kRunning)) {
        (void)internal::WriteCancelled(run->plan, run->plan.tasks[i], "the run was cancelled");
      }
    }
    return absl::CancelledError(absl::StrCat("processing of ", run->plan.take_dir, " cancelled"));
  }

  LocalExecutorOptions options_;
};

}  // namespace

std::unique_ptr<GraphExecutor> MakeLocalExecutor(const LocalExecutorOptions& options) {
  return std::make_unique<LocalExecutor>(options);
}

}  // namespace stage::processing
