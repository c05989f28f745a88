// The Slurm executor (graph_executor.h): a first tiny job checks that a compute node reads the take; then one job array
// per stage (an element per chunk of frames that must run), each after the arrays it reads (aftercorr where chunk i
// needs only chunk i, afterok otherwise; --kill-on-invalid-dep, so a failure cancels what waits for it), submitted
// with sbatch --parsable and watched through squeue --json and the tasks' status files.
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <random>
#include <set>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "graph_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/common/subprocess.h"
#include "stage/processing/graph_executor.h"

namespace stage::processing {
namespace fs = std::filesystem;

absl::Status SlurmOptions::Validate() const {
  if (poll_ms < 10 || poll_ms > 600000) {
    return absl::InvalidArgumentError(absl::StrCat("slurm executor: poll_ms ", poll_ms, " is not in 10..600000"));
  }
  if (probe_timeout_s < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("slurm executor: probe_timeout_s ", probe_timeout_s, " is not >= 1"));
  }
  for (const auto& [stage, r] : resources) {
    if (r.cpus < 1 || r.cpus > 4096) {
      return absl::InvalidArgumentError(
          absl::StrCat("slurm executor: ", GraphStageName(stage), "'s cpus ", r.cpus, " is not in 1..4096"));
    }
  }
  return absl::OkStatus();
}

namespace {

// The batch script every array runs: task BASE + the array index, up to ATTEMPTS times, then its failure recorded.
constexpr const char* kTaskScript = R"SH(#!/bin/bash
# A FaStage processing task on a Slurm node (written by stage-process run --executor slurm; docs/processing.md).
# Arguments: PROGRAM RUN_DIR BASE ATTEMPTS RUN_ID. Runs task BASE + SLURM_ARRAY_TASK_ID of RUN_DIR/plan.json (of run
# RUN_ID), again when it fails, ATTEMPTS times in all (within this job: a timeout or a lost node ends them all); after
# the last failure the task's status file says so.
set -u
program=$1 run_dir=$2 base=$3 attempts=$4 run_id=$5
task=$((base + ${SLURM_ARRAY_TASK_ID:-0}))
code=0
for ((attempt = 1; attempt <= attempts; ++attempt)); do
  echo "fastage: task $task attempt $attempt on $(hostname), job ${SLURM_JOB_ID:-?}" >&2
  "$program" task --run-dir "$run_dir" --task "$task" --attempt "$attempt" --run-id "$run_id" && exit 0
  code=$?
  echo "fastage: task $task attempt $attempt failed (exit code $code)" >&2
done
"$program" task --run-dir "$run_dir" --task "$task" --attempt "$attempts" --run-id "$run_id" \
  --give-up "failed $attempts time(s), the last with exit code $code"
exit 1
)SH";

struct Submitted {
  GraphStage stage;
  std::string job;          // the array's job id
  std::vector<int> chunks;  // its elements
};

// One job's element as squeue shows it: in the queue (pending, running, completing) or ended, with Slurm's reason.
struct QueueEntry {
  bool in_queue = false;
  std::string state, reason;
};

class SlurmExecutor final : public GraphExecutor {
 public:
  explicit SlurmExecutor(SlurmOptions options) : options_(std::move(options)) {
    if (options_.program.empty()) options_.program = DefaultTaskProgram();
  }
  absl::string_view name() const override { return "slurm"; }

  absl::Status Execute(const GraphPlan& plan, const GraphEvents& events,
                       const std::function<bool()>& cancelled) override {
    STAGE_RETURN_IF_ERROR(options_.Validate());
    scratch_ = plan.run_dir + "/slurm";
    std::error_code ec;
    fs::create_directories(scratch_, ec);
    if (ec) return absl::PermissionDeniedError(absl::StrCat(scratch_, ": cannot create: ", ec.message()));
    STAGE_RETURN_IF_ERROR(WriteFileAtomically(scratch_ + "/task.sh", kTaskScript));
    fs::permissions(scratch_ + "/task.sh", fs::perms::owner_all | fs::perms::group_read | fs::perms::group_exec |
                                               fs::perms::others_read | fs::perms::others_exec);
    STAGE_RETURN_IF_ERROR(CheckArraySize(plan));
    STAGE_RETURN_IF_ERROR(Probe(plan, events, cancelled));
    std::vector<Submitted> submitted;
    for (GraphStage stage : plan.stages) {
      auto job = SubmitStage(plan, stage, submitted);
      if (!job.ok()) {
        Cancel(submitted);
        return job.status();
      }
      if (!job->job.empty()) {
        if (events) {
          events(absl::StrCat(GraphStageName(stage), ": Slurm job ", job->job, ", array ",
                              absl::StrJoin(job->chunks, ",")));
        }
        submitted.push_back(*std::move(job));
      }
    }
    absl::Status watched = Watch(plan, submitted, events, cancelled);
    // Whatever ended the watch, no job of this run outlives it unwatched.
    if (!watched.ok()) Cancel(submitted);
    return watched;
  }

 private:
  std::string Tool(const std::string& name) const {
    return options_.bin_dir.empty() ? name : options_.bin_dir + "/" + name;
  }

  // Runs a Slurm command: its stdout, or an error with its stderr.
  absl::StatusOr<std::string> Command(const std::vector<std::string>& argv) const {
    const std::string out = absl::StrCat(scratch_, "/cmd.", getpid(), ".out");
    const std::string err = absl::StrCat(scratch_, "/cmd.", getpid(), ".err");
    SubprocessOptions o;
    o.argv = argv;
    o.stdout_path = out;
    o.stderr_path = err;
    STAGE_ASSIGN_OR_RETURN(auto child, Subprocess::Spawn(o));
    const std::optional<ExitInfo> exit = child->Wait(std::chrono::seconds(120));
    if (!exit) {
      child->Terminate(std::chrono::seconds(1));
      return absl::DeadlineExceededError(absl::StrCat(argv[0], " did not answer in 120 s"));
    }
    auto text = ReadFileToString(out, "output");
    auto message = ReadFileToString(err, "errors");
    if (!exit->ok()) {
      return absl::UnavailableError(absl::StrCat(absl::StrJoin(argv, " "), ": ", exit->Describe(), ": ",
                                                 absl::StripAsciiWhitespace(message.ok() ? *message : "")));
    }
    return text.ok() ? *text : "";
  }

  std::vector<std::string> CommonFlags(const GraphPlan& plan) const {
    std::vector<std::string> flags = {"--parsable", "--chdir=" + plan.run_dir};
    if (!options_.partition.empty()) flags.push_back("--partition=" + options_.partition);
    if (!options_.account.empty()) flags.push_back("--account=" + options_.account);
    flags.insert(flags.end(), options_.sbatch_args.begin(), options_.sbatch_args.end());
    return flags;
  }

  // A first tiny job: can a compute node read the take and write beside it?
  absl::Status Probe(const GraphPlan& plan, const GraphEvents& events, const std::function<bool()>& cancelled) {
    const std::string mark = absl::StrCat(scratch_, "/probe.", std::random_device{}());
    const std::string log = plan.run_dir + "/logs/probe.log";
    std::vector<std::string> argv = {Tool("sbatch")};
    for (std::string& f : CommonFlags(plan)) argv.push_back(std::move(f));
    argv.insert(argv.end(), {"--job-name=fastage-probe", "--output=" + log, "--time=" + ProbeTime(), "--wrap",
                             absl::StrCat("test -r '", plan.take_dir, "/take.json' && hostname > '", mark, "'")});
    STAGE_ASSIGN_OR_RETURN(const std::string out, Command(argv));
    const std::string job = ParsableId(out);
    if (events) events(absl::StrCat("probe: Slurm job ", job, " (does a compute node read the take?)"));
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(options_.probe_timeout_s);
    while (true) {
      STAGE_ASSIGN_OR_RETURN(auto queue, Queue());
      const auto it = queue.find({job, -1});
      if (it == queue.end() || !it->second.in_queue) break;
      if ((cancelled && cancelled()) || std::chrono::steady_clock::now() > deadline) {
        (void)Command({Tool("scancel"), job});
        return cancelled && cancelled()
                   ? absl::CancelledError("processing cancelled while the probe job waited")
                   : absl::DeadlineExceededError(absl::StrCat("the probe job ", job, " did not run within ",
                                                              options_.probe_timeout_s, " s (is the partition up?)"));
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(options_.poll_ms));
    }
    auto host = ReadFileToString(mark, "probe");
    if (!host.ok()) {
      return absl::FailedPreconditionError(absl::StrCat(
          "the take ", plan.take_dir,
          " is not readable, or its processing directory not writable, from the compute "
          "nodes (probe job ",
          job, " left no mark; its log: ", log, "): put the take on a file system every node mounts at the same path"));
    }
    std::error_code ec;
    fs::remove(mark, ec);
    if (events) events(absl::StrCat("probe: ", absl::StripAsciiWhitespace(*host), " reads the take"));
    return absl::OkStatus();
  }

  std::string ProbeTime() const { return "5"; }

  // A stage's chunks are its array's indices: the cluster's MaxArraySize (scontrol show config) bounds them.
  absl::Status CheckArraySize(const GraphPlan& plan) const {
    int chunks = 0;
    for (const GraphTask& t : plan.tasks) chunks = std::max(chunks, t.chunk + 1);
    STAGE_ASSIGN_OR_RETURN(const std::string config, Command({Tool("scontrol"), "show", "config"}));
    for (absl::string_view line : absl::StrSplit(config, '\n')) {
      if (!absl::ConsumePrefix(&line, "MaxArraySize")) continue;
      int max = 0;
      const size_t eq = line.find('=');
      if (eq == absl::string_view::npos || !absl::SimpleAtoi(absl::StripAsciiWhitespace(line.substr(eq + 1)), &max)) {
        break;
      }
      if (chunks >= max) {
        return absl::InvalidArgumentError(absl::StrCat(
            plan.take_dir, ": ", chunks, " chunks of a stage, but the cluster's MaxArraySize is ", max,
            ": give --chunk-frames at least ", (plan.last_frame - plan.first_frame + max - 2) / (max - 1)));
      }
    }
    return absl::OkStatus();
  }

  static std::string ParsableId(const std::string& out) {
    // "JOBID" or "JOBID;CLUSTER"
    std::string id(absl::StripAsciiWhitespace(out));
    return id.substr(0, id.find(';'));
  }

  absl::StatusOr<Submitted> SubmitStage(const GraphPlan& plan, GraphStage stage,
                                        const std::vector<Submitted>& before) const {
    Submitted s{stage, "", {}};
    int base = -1;
    for (const GraphTask* t : plan.TasksOf(stage)) {
      if (base < 0) base = plan.Find(stage, t->chunk);
      if (t->needed) s.chunks.push_back(t->chunk);
    }
    if (s.chunks.empty()) return s;
    // What it waits for: the arrays of the stages it reads; chunk to chunk when both run the same chunks.
    std::vector<std::string> after;
    for (const StageInput& in : SpecOf(stage).inputs) {
      for (const Submitted& b : before) {
        if (b.stage != in.stage) continue;
        const bool corr = plan.ChunkToChunk(stage) && b.chunks == s.chunks;
        after.push_back(absl::StrCat(corr ? "aftercorr:" : "afterok:", b.job));
      }
    }
    const auto r = options_.resources.find(stage);
    const SlurmStageResources res = r == options_.resources.end() ? SlurmStageResources{} : r->second;
    std::vector<std::string> argv = {Tool("sbatch")};
    for (std::string& f : CommonFlags(plan)) argv.push_back(std::move(f));
    // The take and the stage in the name: `squeue` shows whose they are, `scancel --name` ends a run's jobs.
    argv.push_back(
        absl::StrCat("--job-name=fastage-", fs::path(plan.take_dir).filename().string(), "-", GraphStageName(stage)));
    argv.push_back("--array=" + absl::StrJoin(s.chunks, ","));
    argv.push_back(absl::StrCat("--output=", plan.run_dir, "/logs/", GraphStageName(stage), ".%a.log"));
    argv.push_back("--open-mode=append");
    argv.push_back(absl::StrCat("--cpus-per-task=", res.cpus));
    if (!res.memory.empty()) argv.push_back("--mem=" + res.memory);
    const std::string time = res.time_limit.empty() ? options_.time_limit : res.time_limit;
    if (!time.empty()) argv.push_back("--time=" + time);
    if (!after.empty()) {
      argv.push_back("--dependency=" + absl::StrJoin(after, ","));
      argv.push_back("--kill-on-invalid-dep=yes");
    }
    argv.insert(argv.end(), {scratch_ + "/task.sh", options_.program, plan.run_dir, std::to_string(base),
                             std::to_string(plan.options.retries + 1), plan.run_id});
    STAGE_ASSIGN_OR_RETURN(const std::string out, Command(argv));
    s.job = ParsableId(out);
    if (s.job.empty())
      return absl::UnavailableError(absl::StrCat("sbatch printed no job id for ", GraphStageName(stage)));
    return s;
  }

  // This user's jobs in squeue, by (job id, array element; -1 for a job that is not an array's element).
  absl::StatusOr<std::map<std::pair<std::string, int>, QueueEntry>> Queue() const {
    // A busy controller may not answer once: three tries, a few seconds apart.
    absl::StatusOr<std::string> out;
    for (int attempt = 0; attempt < 3; ++attempt) {
      if (attempt > 0) std::this_thread::sleep_for(std::chrono::seconds(3));
      out = Command({Tool("squeue"), "--json", "--me"});
      if (out.ok()) break;
    }
    if (!out.ok()) return out.status();
    const nlohmann::json j = nlohmann::json::parse(*out, nullptr, false);
    if (j.is_discarded() || !j.contains("jobs")) return absl::DataLossError("squeue --json: not the JSON expected");
    try {
      return ParseQueue(j);
    } catch (const nlohmann::json::exception& e) {
      return absl::DataLossError(absl::StrCat("squeue --json: ", e.what()));
    }
  }

  // Slurm 22.05's squeue JSON; later releases' shapes too (a state as a list, numbers as {"set", "number"} objects).
  static std::map<std::pair<std::string, int>, QueueEntry> ParseQueue(const nlohmann::json& j) {
    auto number = [](const nlohmann::json& job, const char* key) -> std::optional<int64_t> {
      if (!job.contains(key)) return std::nullopt;
      const nlohmann::json& v = job[key];
      if (v.is_number_integer()) return v.get<int64_t>();
      if (v.is_object() && v.value("set", false) && v.contains("number")) return v["number"].get<int64_t>();
      return std::nullopt;
    };
    auto text = [](const nlohmann::json& job, const char* key) -> std::string {
      if (!job.contains(key)) return "";
      const nlohmann::json& v = job[key];
      if (v.is_string()) return v.get<std::string>();
      if (v.is_array() && !v.empty() && v[0].is_string()) return v[0].get<std::string>();
      return "";
    };
    std::map<std::pair<std::string, int>, QueueEntry> queue;
    static const std::set<std::string> kInQueue = {"PENDING",   "RUNNING",  "CONFIGURING", "COMPLETING",
                                                   "SUSPENDED", "REQUEUED", "RESIZING",    "SIGNALING"};
    for (const auto& job : j["jobs"]) {
      QueueEntry e;
      e.state = text(job, "job_state");
      e.reason = text(job, "state_reason");
      e.in_queue = kInQueue.count(e.state) > 0;
      const std::string id = std::to_string(number(job, "job_id").value_or(0));
      const int64_t array = number(job, "array_job_id").value_or(0);
      const std::optional<int64_t> task = number(job, "array_task_id");
      if (array != 0 && task) {
        queue[{std::to_string(array), static_cast<int>(*task)}] = e;
      } else if (array != 0) {
        // A pending array's elements not yet split out: "0-3", "1,4-5", "0-9%2".
        for (absl::string_view part : absl::StrSplit(text(job, "array_task_string"), ',', absl::SkipEmpty())) {
          part = part.substr(0, part.find('%'));
          const std::vector<std::string> ends = absl::StrSplit(part, '-');
          int a = 0, b = 0;
          if (!absl::SimpleAtoi(ends[0], &a)) continue;
          b = a;
          if (ends.size() > 1 && !absl::SimpleAtoi(ends[1], &b)) continue;
          for (int k = a; k <= b; ++k) queue[{std::to_string(array), k}] = e;
        }
      }
      queue[{id, -1}] = e;
    }
    return queue;
  }

  void Cancel(const std::vector<Submitted>& submitted) const {
    for (const Submitted& s : submitted) (void)Command({Tool("scancel"), s.job});
  }

  // A task the watch follows: its array and element, whether it has ended, the attempt last seen.
  struct Watched {
    int task;
    std::string job;
    int chunk;
    bool finished = false;
    int attempt = 0;
    std::chrono::steady_clock::time_point completed_at{};
  };
  using QueueView = std::map<std::pair<std::string, int>, QueueEntry>;

  absl::Status Watch(const GraphPlan& plan, const std::vector<Submitted>& submitted, const GraphEvents& events,
                     const std::function<bool()>& cancelled) const;
  // One look at a task still open: its state (from its status file, or written here when Slurm ended it), lines of
  // news; true while it is still to end.
  static bool Look(const GraphPlan& plan, const QueueView& queue, Watched* w, TaskState* state,
                   std::vector<std::string>* news);

  SlurmOptions options_;
  std::string scratch_;
};

absl::Status SlurmExecutor::Watch(const GraphPlan& plan, const std::vector<Submitted>& submitted,
                                  const GraphEvents& events, const std::function<bool()>& cancelled) const {
  std::vector<Watched> watched;
  for (const Submitted& s : submitted) {
    for (int c : s.chunks) watched.push_back({plan.Find(s.stage, c), s.job, c});
  }
  // The tasks' states as last seen: status.json is written when they change, before the news of it goes out.
  std::vector<TaskState> states(plan.tasks.size(), TaskState::kPending), written = states;
  while (true) {
    if (cancelled && cancelled()) {
      Cancel(submitted);
      for (const Watched& w : watched) {
        if (!w.finished) (void)internal::WriteCancelled(plan, plan.tasks[w.task], "the run was cancelled");
      }
      return absl::CancelledError(absl::StrCat("processing of ", plan.take_dir, " cancelled"));
    }
    STAGE_ASSIGN_OR_RETURN(const auto queue, Queue());
    size_t open = 0;
    std::vector<std::string> news;
    for (Watched& w : watched) {
      if (!w.finished && Look(plan, queue, &w, &states[w.task], &news)) ++open;
    }
    if (states != written) {
      (void)WriteGraphSummary(plan, GraphProgress(plan, states), false);
      written = states;
    }
    if (events) {
      for (const std::string& line : news) events(line);
    }
    if (open == 0) return absl::OkStatus();
    std::this_thread::sleep_for(std::chrono::milliseconds(options_.poll_ms));
  }
}

bool SlurmExecutor::Look(const GraphPlan& plan, const QueueView& queue, Watched* w, TaskState* state,
                         std::vector<std::string>* news) {
  const GraphTask& task = plan.tasks[w->task];
  const std::string name = plan.TaskName(task), path = StatusPath(plan, task);
  const auto q = queue.find({w->job, w->chunk});
  const bool in_queue = q != queue.end() && q->second.in_queue;
  auto status = ReadTaskStatus(path);
  if (status.ok()) {
    *state = status->state;
    if (status->attempt > w->attempt) {
      if (w->attempt > 0) news->push_back(absl::StrCat(name, ": attempt ", status->attempt, " (a retry)"));
      if (status->state == TaskState::kRunning) {
        news->push_back(absl::StrCat(name, " running on ", status->host, " (pid ", status->pid, ")"));
      }
      w->attempt = status->attempt;
    }
  }
  if (status.ok() && status->state == TaskState::kDone) {
    w->finished = true;
    news->push_back(absl::StrCat(name, " done: ", status->message));
    return false;
  }
  if (in_queue) return true;
  // Slurm says it completed but its status file does not say done yet (a shared file system's cache): wait for it a
  // while before calling it anything else.
  if (q != queue.end() && q->second.state == "COMPLETED" && !(status.ok() && status->state == TaskState::kFailed)) {
    if (w->completed_at == std::chrono::steady_clock::time_point{}) w->completed_at = std::chrono::steady_clock::now();
    if (std::chrono::steady_clock::now() - w->completed_at < std::chrono::seconds(60)) return true;
  }
  // Out of the queue without being done: failed (its status says so), or ended by Slurm.
  w->finished = true;
  if (status.ok() && status->state == TaskState::kFailed) {
    news->push_back(absl::StrCat(name, " failed: ", status->message, " (log: ", status->log, ")"));
    return false;
  }
  TaskStatus s = status.ok() ? *status : TaskStatus{};
  const std::string slurm =
      q == queue.end() ? "gone from the queue" : absl::StrCat(q->second.state, ", ", q->second.reason);
  s.state = status.ok() ? TaskState::kFailed : TaskState::kCancelled;
  s.message = status.ok() ? absl::StrCat("its Slurm job ended while it ran (", slurm, ")")
                          : absl::StrCat("not run: Slurm ended its job (", slurm, ")");
  s.log = LogPath(plan, task);
  (void)WriteTaskStatus(path, s);
  *state = s.state;
  news->push_back(absl::StrCat(name, " ", TaskStateName(s.state), ": ", s.message));
  return false;
}

}  // namespace

std::unique_ptr<GraphExecutor> MakeSlurmExecutor(const SlurmOptions& options) {
  return std::make_unique<SlurmExecutor>(options);
}

}  // namespace stage::processing
