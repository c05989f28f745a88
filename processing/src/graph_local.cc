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

namespace internal {

// Marks every needed task after `failed` (transitively) cancelled, in its status file and in `state`.
void CancelAfter(const GraphPlan& plan, int failed, std::vector<TaskState>* state, const GraphEvents& events) {
  for (size_t i = 0; i < plan.tasks.size(); ++i) {
    if (!plan.tasks[i].needed || (*state)[i] != TaskState::kPending) continue;
    const std::vector<int> deps = Dependencies(plan, static_cast<int>(i), true);
    const bool after = std::any_of(deps.begin(), deps.end(),
                                   [&](int d) { return d == failed || (*state)[d] == TaskState::kCancelled; });
    if (!after) continue;
    (*state)[i] = TaskState::kCancelled;
    TaskStatus s;
    s.state = TaskState::kCancelled;
    s.message = absl::StrCat("not run: ", plan.TaskName(plan.tasks[failed]), " failed");
    s.log = LogPath(plan, plan.tasks[i]);
    (void)WriteTaskStatus(StatusPath(plan, plan.tasks[i]), s);
    if (events) events(absl::StrCat(plan.TaskName(plan.tasks[i]), " cancelled: ", s.message));
  }
}

}  // namespace internal

namespace {

class LocalExecutor final : public GraphExecutor {
 public:
  explicit LocalExecutor(LocalExecutorOptions options) : options_(std::move(options)) {
    if (options_.program.empty()) options_.program = DefaultTaskProgram();
  }
  absl::string_view name() const override { return "local"; }

  absl::Status Execute(const GraphPlan& plan, const GraphEvents& events,
                       const std::function<bool()>& cancelled) override {
    STAGE_RETURN_IF_ERROR(options_.Validate());
    const size_t n = plan.tasks.size();
    std::vector<TaskState> state(n, TaskState::kPending);
    std::vector<int> attempts(n, 0);
    std::vector<std::unique_ptr<Subprocess>> running(n);
    auto finished = [&](size_t i) {
      return !plan.tasks[i].needed || state[i] == TaskState::kDone || state[i] == TaskState::kFailed ||
             state[i] == TaskState::kCancelled;
    };
    while (true) {
      size_t active = 0, open = 0;
      for (size_t i = 0; i < n; ++i) {
        if (running[i]) ReapIfEnded(plan, i, events, &state, &attempts, &running);
      }
      if (cancelled && cancelled()) return StopAll(plan, &state, &running);
      for (size_t i = 0; i < n; ++i) {
        if (running[i]) ++active;
        if (!finished(i)) ++open;
      }
      if (open == 0) return absl::OkStatus();
      for (size_t i = 0; i < n && active < static_cast<size_t>(options_.jobs); ++i) {
        if (state[i] != TaskState::kPending || !plan.tasks[i].needed || running[i] || !Ready(plan, i, state)) continue;
        STAGE_RETURN_IF_ERROR(Start(plan, i, ++attempts[i], events, &running));
        state[i] = TaskState::kRunning;
        ++active;
      }
      if (active == 0) return absl::InternalError("local executor: tasks wait for none running (a cycle?)");
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }

 private:
  static bool Ready(const GraphPlan& plan, size_t i, const std::vector<TaskState>& state) {
    for (int d : internal::Dependencies(plan, static_cast<int>(i), true)) {
      if (state[d] != TaskState::kDone) return false;
    }
    return true;
  }

  absl::Status Start(const GraphPlan& plan, size_t i, int attempt, const GraphEvents& events,
                     std::vector<std::unique_ptr<Subprocess>>* running) const {
    SubprocessOptions o;
    o.argv = {options_.program,        "task",     "--run-dir", plan.run_dir, "--task", std::to_string(i), "--attempt",
              std::to_string(attempt), "--run-id", plan.run_id};
    o.stdout_path = o.stderr_path = LogPath(plan, plan.tasks[i]);
    o.append = true;
    STAGE_ASSIGN_OR_RETURN((*running)[i], Subprocess::Spawn(o));
    (void)WriteGraphSummary(plan, GraphProgress(plan), false);
    if (events) {
      events(absl::StrCat(plan.TaskName(plan.tasks[i]), " started (frames ", plan.tasks[i].first, ":",
                          plan.tasks[i].last, ", attempt ", attempt, ", pid ", (*running)[i]->pid(), ")"));
    }
    return absl::OkStatus();
  }

  // A task's process that has ended: done, run again, or failed (and what waits for it cancelled).
  void ReapIfEnded(const GraphPlan& plan, size_t i, const GraphEvents& events, std::vector<TaskState>* state,
                   std::vector<int>* attempts, std::vector<std::unique_ptr<Subprocess>>* running) const {
    const std::optional<ExitInfo> exit = (*running)[i]->Poll();
    if (!exit) return;
    (*running)[i].reset();
    struct Summary {
      const GraphPlan& plan;
      ~Summary() { (void)WriteGraphSummary(plan, GraphProgress(plan), false); }
    } summary{plan};  // once this task's end is in its status file
    const std::string name = plan.TaskName(plan.tasks[i]);
    const std::string path = StatusPath(plan, plan.tasks[i]);
    auto status = ReadTaskStatus(path);
    if (exit->ok() && status.ok() && status->state == TaskState::kDone) {
      (*state)[i] = TaskState::kDone;
      if (events) events(absl::StrCat(name, " done: ", status->message));
      return;
    }
    const std::string why = status.ok() && status->state == TaskState::kFailed ? status->message : exit->Describe();
    if ((*attempts)[i] <= plan.options.retries) {
      if (events) events(absl::StrCat(name, " attempt ", (*attempts)[i], " failed (", why, "): retrying"));
      (*state)[i] = TaskState::kPending;
      return;
    }
    (*state)[i] = TaskState::kFailed;
    if (!status.ok() || status->state != TaskState::kFailed) {
      TaskStatus s = status.ok() ? *status : TaskStatus{};
      s.state = TaskState::kFailed;
      s.attempt = (*attempts)[i];
      s.message = why;
      s.log = LogPath(plan, plan.tasks[i]);
      (void)WriteTaskStatus(path, s);
    }
    if (events) events(absl::StrCat(name, " failed after ", (*attempts)[i], " attempt(s): ", why));
    internal::CancelAfter(plan, static_cast<int>(i), state, events);
  }

  static absl::Status StopAll(const GraphPlan& plan, std::vector<TaskState>* state,
                              std::vector<std::unique_ptr<Subprocess>>* running) {
    for (size_t i = 0; i < running->size(); ++i) {
      if ((*running)[i]) (*running)[i]->Terminate(std::chrono::seconds(5));
      if ((*state)[i] == TaskState::kPending || (*state)[i] == TaskState::kRunning) {
        TaskStatus s;
        s.state = TaskState::kCancelled;
        s.message = "the run was cancelled";
        s.log = LogPath(plan, plan.tasks[i]);
        if (plan.tasks[i].needed) (void)WriteTaskStatus(StatusPath(plan, plan.tasks[i]), s);
      }
    }
    return absl::CancelledError(absl::StrCat("processing of ", plan.take_dir, " cancelled"));
  }

  LocalExecutorOptions options_;
};

}  // namespace

std::unique_ptr<GraphExecutor> MakeLocalExecutor(const LocalExecutorOptions& options) {
  return std::make_unique<LocalExecutor>(options);
}

}  // namespace stage::processing
