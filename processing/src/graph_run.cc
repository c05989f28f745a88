// A run of the processing graph (graph_executor.h): one at a time per take, planned, executed, reported.
#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "graph_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/graph_executor.h"

namespace stage::processing {
namespace fs = std::filesystem;

std::string DefaultTaskProgram() {
  std::error_code ec;
  const fs::path self = fs::read_symlink("/proc/self/exe", ec);
  return (self.parent_path() / "stage-process").string();
}

namespace {

// The run's lock on the take: an flock on <run_dir>/lock held while the run lasts, the holder's pid written in it.
class RunLock {
 public:
  static absl::StatusOr<std::unique_ptr<RunLock>> Take(const std::string& run_dir) {
    std::error_code ec;
    fs::create_directories(run_dir, ec);
    if (ec) return absl::PermissionDeniedError(absl::StrCat(run_dir, ": cannot create: ", ec.message()));
    const std::string path = run_dir + "/lock";
    const int fd = open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0) return absl::PermissionDeniedError(absl::StrCat(path, ": cannot open"));
    if (flock(fd, LOCK_EX | LOCK_NB) != 0) {
      char pid[32] = {};
      (void)!pread(fd, pid, sizeof(pid) - 1, 0);
      close(fd);
      return absl::FailedPreconditionError(
          absl::StrCat(run_dir, ": another run is processing this take (pid ", pid, ")"));
    }
    const std::string mine = std::to_string(getpid());
    (void)!ftruncate(fd, 0);
    (void)!pwrite(fd, mine.data(), mine.size(), 0);
    return std::unique_ptr<RunLock>(new RunLock(fd));
  }
  ~RunLock() { close(fd_); }

 private:
  explicit RunLock(int fd) : fd_(fd) {}
  int fd_;
};

std::vector<TaskFailure> Failures(const GraphPlan& plan) {
  std::vector<TaskFailure> out;
  for (const GraphTask& t : plan.tasks) {
    if (!t.needed) continue;
    auto status = ReadTaskStatus(StatusPath(plan, t));
    if (status.ok() && status->state == TaskState::kDone) continue;
    TaskFailure f{plan.TaskName(t), TaskState::kFailed, "", LogPath(plan, t)};
    if (!status.ok()) {
      f.state = TaskState::kCancelled;
      f.message = "never ran";
    } else {
      f.state = status->state == TaskState::kCancelled ? TaskState::kCancelled : TaskState::kFailed;
      f.message = status->state == TaskState::kRunning || status->state == TaskState::kPending
                      ? absl::StrCat("ended while ", TaskStateName(status->state), " (attempt ", status->attempt, ")")
                      : status->message;
    }
    out.push_back(std::move(f));
  }
  return out;
}

}  // namespace

absl::StatusOr<GraphReport> RunGraph(const GraphOptions& options, GraphExecutor& executor, const GraphEvents& events,
                                     const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_ASSIGN_OR_RETURN(auto lock, RunLock::Take(GraphRunDir(options.take_dir)));
  GraphReport report;
  report.executor = std::string(executor.name());
  STAGE_ASSIGN_OR_RETURN(report.plan, PlanGraph(options));
  const GraphPlan& plan = report.plan;
  report.plan.run_id = absl::StrFormat("%016x", std::random_device{}() * 0x100000000ull + std::random_device{}());
  // Written even when nothing is to do: the take's books then say so, not what an earlier run left.
  STAGE_RETURN_IF_ERROR(WritePlan(plan));
  if (plan.needed_tasks() == 0) {
    report.nothing_to_do = true;
    report.stages = GraphProgress(plan);
    STAGE_RETURN_IF_ERROR(WriteGraphSummary(plan, report.stages, true));
    if (events) events("every output asked for is up to date: nothing to do");
    return report;
  }
  STAGE_RETURN_IF_ERROR(WriteGraphSummary(
      plan, GraphProgress(plan, std::vector<TaskState>(plan.tasks.size(), TaskState::kPending)), false));
  if (events) {
    events(absl::StrCat(plan.needed_tasks(), " of ", plan.tasks.size(), " task(s) to run, frames [", plan.first_frame,
                        ", ", plan.last_frame, "), executor ", executor.name()));
  }
  const absl::Status run = executor.Execute(plan, events, cancelled);
  report.stages = GraphProgress(plan);
  report.failures = Failures(plan);
  STAGE_RETURN_IF_ERROR(WriteGraphSummary(plan, report.stages, true));
  if (!run.ok()) return run;
  return report;
}

std::string FormatGraphPlan(const GraphPlan& plan) {
  std::string out = absl::StrFormat("%-16s %-8s %-8s %s\n", "task", "frames", "runs", "why");
  for (const GraphTask& t : plan.tasks) {
    absl::StrAppendFormat(&out, "%-16s %-8s %-8s %s\n", plan.TaskName(t), absl::StrCat(t.first, ":", t.last),
                          t.needed ? "yes" : "no", t.reason);
  }
  return out;
}

std::string FormatGraphReport(const GraphReport& report) {
  if (report.nothing_to_do) return "every output asked for is up to date: nothing to do\n";
  std::string out = absl::StrFormat("%-12s %-7s %-11s %-6s %-7s %s\n", "stage", "units", "up to date", "tasks",
                                    "failed", "cancelled");
  for (const StageProgress& p : report.stages) {
    absl::StrAppendFormat(&out, "%-12s %-7d %-11d %-6d %-7d %d\n", GraphStageName(p.stage), p.units, p.up_to_date,
                          p.tasks, p.failed, p.cancelled);
  }
  for (const TaskFailure& f : report.failures) {
    absl::StrAppend(&out, f.task, " ", TaskStateName(f.state), ": ", f.message, " (log: ", f.log, ")\n");
  }
  return out;
}

std::string GraphReportJson(const GraphReport& report) {
  nlohmann::ordered_json j;
  j["take_dir"] = report.plan.take_dir;
  j["executor"] = report.executor;
  j["frames"] = {report.plan.first_frame, report.plan.last_frame};
  j["nothing_to_do"] = report.nothing_to_do;
  j["ok"] = report.ok();
  j["stages"] = nlohmann::json::array();
  for (const StageProgress& p : report.stages) j["stages"].push_back(internal::StageJson(p, true));
  j["tasks"] = nlohmann::json::array();
  for (const GraphTask& t : report.plan.tasks) {
    nlohmann::ordered_json task{
        {"task", report.plan.TaskName(t)}, {"frames", {t.first, t.last}}, {"ran", t.needed}, {"why", t.reason}};
    if (t.needed) {
      if (auto s = ReadTaskStatus(StatusPath(report.plan, t)); s.ok()) {
        task["state"] = TaskStateName(s->state);
        task["attempts"] = s->attempt;
        task["units_made"] = s->made;
        task["message"] = s->message;
      }
      task["log"] = LogPath(report.plan, t);
    }
    j["tasks"].push_back(std::move(task));
  }
  j["failures"] = nlohmann::json::array();
  for (const TaskFailure& f : report.failures) {
    j["failures"].push_back(
        {{"task", f.task}, {"state", TaskStateName(f.state)}, {"message", f.message}, {"log", f.log}});
  }
  return j.dump();
}

}  // namespace stage::processing
