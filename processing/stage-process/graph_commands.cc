// `stage-process run` and `stage-process task` (graph_commands.h).
#include "graph_commands.h"

#include <unistd.h>

#include <cstdlib>
#include <iostream>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "stage/common/cli.h"
#include "stage/common/file_util.h"
#include "stage/common/shutdown.h"
#include "stage/common/status.h"

namespace stage::process {
namespace {

constexpr const char* kProgram = "stage-process";
using processing::GraphStage;

// "mvs:VALUE" -> (kMvs, VALUE); an error naming the flag otherwise.
absl::StatusOr<std::pair<GraphStage, std::string>> StagePrefixed(const std::string& flag, const std::string& text,
                                                                 char separator) {
  const size_t at = text.find(separator);
  auto stage = at == std::string::npos ? std::nullopt : processing::ParseGraphStage(text.substr(0, at));
  if (!stage) {
    return absl::InvalidArgumentError(absl::StrCat(flag, " ", text, ": expected STAGE", std::string(1, separator),
                                                   "VALUE with STAGE one of calibrate, mvs, photometric, fit, "
                                                   "textures, stabilize"));
  }
  return std::make_pair(*stage, text.substr(at + 1));
}

// The last "stage-process: error: ..." line of a task's log since its last attempt began (the log holds every
// attempt's): the stage's own error; "" when that attempt wrote none (killed).
std::string LastError(const std::string& log) {
  auto text = ReadFileToString(log, "log");
  if (!text.ok()) return "";
  std::string last;
  for (absl::string_view line : absl::StrSplit(*text, '\n')) {
    if (absl::StartsWith(line, "stage-process task: ") && absl::StrContains(line, " attempt ")) last.clear();
    if (absl::ConsumePrefix(&line, "stage-process: error: ")) last = std::string(line);
  }
  return last;
}

// "mvs 2/2, photometric 1/2 (1 running)": units up to date per stage.
std::string ProgressWords(const std::vector<processing::StageProgress>& progress) {
  std::vector<std::string> words;
  for (const processing::StageProgress& p : progress) {
    std::string w = absl::StrCat(processing::GraphStageName(p.stage), " ", p.up_to_date, "/", p.units);
    if (p.running > 0) absl::StrAppend(&w, " (", p.running, " running)");
    if (p.failed > 0) absl::StrAppend(&w, " (", p.failed, " failed)");
    if (p.cancelled > 0) absl::StrAppend(&w, " (", p.cancelled, " cancelled)");
    words.push_back(std::move(w));
  }
  return absl::StrJoin(words, ", ");
}

}  // namespace

void GraphCommands::Add(CLI::App& parent) {
  AddRun(parent);
  AddStatusAndTask(parent);
}

void GraphCommands::AddRun(CLI::App& parent) {
  run_ = parent.add_subcommand(
      "run",
      "The processing graph over a take (docs/processing.md#the-graph): runs, on this machine or on a Slurm cluster, "
      "the tasks that bring the outputs asked for up to date, skipping what is; each output is put in place whole, "
      "with a manifest of what made it (TAKE/derived/STAGE/.../manifest.json); the run's books are in "
      "TAKE/processing (plan.json, status/, logs/)");
  run_->add_option("--take", options_.take_dir, "The take directory (takes/<take-id>)")->required();
  run_->add_option("--stages", stages_,
                   "The outputs asked for, comma-separated: calibrate, mvs, photometric, fit, textures, stabilize "
                   "(default: all but calibrate); the stages they read are added");
  run_->add_option("--frames", frames_, "Virtual frames A:B (B excluded), A: to the end, or A")->capture_default_str();
  run_->add_option("--chunk-frames", options_.chunk_frames, "Frames per task of a per-frame stage")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000000));
  run_->add_option("--calibration", options_.calibration,
                   "Where the cameras are, for the stages that place them: a calibration file or a directory holding "
                   "cameras.json, relative to the take or absolute (default: the rig's nominal models)");
  run_->add_option("--with", with_,
                   "A stage's own flag, STAGE:FLAG (e.g. mvs:--image-scale=0.25); repeat for more. Part of each "
                   "output's manifest: a change redoes that stage and what reads it");
  run_->add_option("--retries", options_.retries, "Runs a failed task again this many times")
      ->capture_default_str()
      ->check(CLI::Range(0, 100));
  run_->add_option("--executor", executor_, "local (this machine) or slurm (sbatch job arrays)")
      ->capture_default_str()
      ->check(CLI::IsMember({"local", "slurm"}));
  run_->add_flag("--dry-run", dry_run_, "Print the plan (each task, whether it runs and why) and run nothing");
  run_->add_flag("--json", json_, "Print the report (or with --dry-run the plan) as JSON on stdout");
  AddExecutorOptions();
}

void GraphCommands::AddExecutorOptions() {
  run_->add_option("--jobs", local_.jobs, "local: tasks at a time")->capture_default_str()->check(CLI::Range(1, 256));
  run_->add_option("--partition", slurm_.partition, "slurm: sbatch --partition");
  run_->add_option("--account", slurm_.account, "slurm: sbatch --account");
  run_->add_option("--time", slurm_.time_limit, "slurm: sbatch --time of every task (e.g. 1:00:00)");
  run_->add_option("--cpus", cpus_, "slurm: --cpus-per-task, N for every stage or STAGE=N; repeat for more");
  run_->add_option("--mem", mem_, "slurm: --mem, SIZE for every stage or STAGE=SIZE (e.g. fit=8G); repeat");
  run_->add_option("--sbatch-arg", slurm_.sbatch_args, "slurm: a further sbatch flag for every job; repeat for more");
  run_->add_option("--slurm-bin-dir", slurm_.bin_dir, "slurm: where sbatch, squeue and scancel are (default: PATH)");
  run_->add_option("--poll-ms", slurm_.poll_ms, "slurm: how often the queue is looked at, ms")->capture_default_str();
}

void GraphCommands::AddStatusAndTask(CLI::App& parent) {
  status_ = parent.add_subcommand(
      "status",
      "Where a take's processing stands (its last or running graph run, TAKE/processing): per stage, its units up to "
      "date and its tasks running, failed or cancelled");
  status_->add_option("--take", options_.take_dir, "The take directory")->required();
  status_->add_flag("--json", json_, "Print it as JSON on stdout");

  task_ = parent.add_subcommand(
      "task",
      "One task of a processing run (what the executors start; docs/processing.md): a stage over the task's frames "
      "into a work directory, then each output put in place with its manifest, the task's status in "
      "RUN_DIR/status/");
  task_->add_option("--run-dir", run_dir_, "The run's directory (TAKE/processing, with plan.json)")->required();
  task_->add_option("--task", task_index_, "The task's index in plan.json")->required();
  task_->add_option("--attempt", attempt_, "Its attempt, from 1")->capture_default_str()->check(CLI::Range(1, 1000));
  task_->add_option("--give-up", give_up_, "Record the task failed with this message, and run nothing");
  task_->add_option("--run-id", run_id_,
                    "The run it belongs to: refused when plan.json is another run's (a job an earlier run left)");
}

bool GraphCommands::Parsed() const { return run_->parsed() || task_->parsed() || status_->parsed(); }

int GraphCommands::Run(const StageCommand& stage_command) {
  if (status_->parsed()) return Status();
  return run_->parsed() ? RunGraph() : RunTask(stage_command);
}

int GraphCommands::Status() {
  // status.json, as the executors keep it up to date (and the controller's catalog reads it).
  const std::string run_dir = processing::GraphRunDir(options_.take_dir);
  auto progress = processing::ReadGraphSummary(run_dir);
  if (!progress.ok()) {
    return ReportFatal(kProgram,
                       absl::Status(progress.status().code(), absl::StrCat(options_.take_dir,
                                                                           ": no processing run (stage-process "
                                                                           "run starts one): ",
                                                                           progress.status().message())));
  }
  if (json_) {
    std::cout << ReadFileToString(run_dir + "/status.json").value_or("{}");
  } else {
    std::cout << options_.take_dir << ": " << ProgressWords(*progress) << "\n";
  }
  return 0;
}

absl::Status GraphCommands::Collect() {
  STAGE_RETURN_IF_ERROR(ParseFrameRange("--frames", frames_, &options_.first_frame, &options_.last_frame));
  for (absl::string_view word : absl::StrSplit(stages_, ',', absl::SkipEmpty())) {
    auto stage = processing::ParseGraphStage(word);
    if (!stage) return absl::InvalidArgumentError(absl::StrCat("--stages: no stage \"", word, "\""));
    options_.stages.push_back(*stage);
  }
  for (const std::string& w : with_) {
    STAGE_ASSIGN_OR_RETURN(auto flag, StagePrefixed("--with", w, ':'));
    options_.stage_args[flag.first].push_back(flag.second);
  }
  for (const std::string& c : cpus_) {
    int n = 0;
    if (c.find('=') == std::string::npos) {
      if (!absl::SimpleAtoi(c, &n)) return absl::InvalidArgumentError(absl::StrCat("--cpus ", c, ": not a number"));
      for (GraphStage s : processing::kGraphStages) slurm_.resources[s].cpus = n;
      continue;
    }
    STAGE_ASSIGN_OR_RETURN(auto v, StagePrefixed("--cpus", c, '='));
    if (!absl::SimpleAtoi(v.second, &n))
      return absl::InvalidArgumentError(absl::StrCat("--cpus ", c, ": not a number"));
    slurm_.resources[v.first].cpus = n;
  }
  for (const std::string& m : mem_) {
    if (m.find('=') == std::string::npos) {
      for (GraphStage s : processing::kGraphStages) slurm_.resources[s].memory = m;
      continue;
    }
    STAGE_ASSIGN_OR_RETURN(auto v, StagePrefixed("--mem", m, '='));
    slurm_.resources[v.first].memory = v.second;
  }
  const bool slurm = executor_ == "slurm";
  for (const char* name :
       {"--partition", "--account", "--time", "--cpus", "--mem", "--sbatch-arg", "--slurm-bin-dir", "--poll-ms"}) {
    if (!slurm && run_->count(name) > 0) {
      return absl::InvalidArgumentError(absl::StrCat(name, " applies to --executor slurm"));
    }
  }
  if (slurm && run_->count("--jobs") > 0) return absl::InvalidArgumentError("--jobs applies to --executor local");
  STAGE_RETURN_IF_ERROR(options_.Validate());
  return slurm ? slurm_.Validate() : local_.Validate();
}

int GraphCommands::RunGraph() {
  if (auto s = Collect(); !s.ok()) return ReportFatal(kProgram, s);
  if (dry_run_) {
    auto plan = processing::PlanGraph(options_);
    if (!plan.ok()) return ReportFatal(kProgram, plan.status());
    if (json_) {
      processing::GraphReport report;
      report.plan = *plan;
      report.executor = executor_;
      report.nothing_to_do = plan->needed_tasks() == 0;
      std::cout << processing::GraphReportJson(report) << "\n";
    } else {
      std::cout << processing::FormatGraphPlan(*plan);
    }
    return 0;
  }
  // Ctrl-C or SIGTERM ends the run: local tasks stopped, Slurm jobs cancelled (scancel), each task's status saying so.
  BlockShutdownSignals();
  bool stopping = false;
  auto cancelled = [&stopping] {
    if (!stopping) stopping = WaitForShutdownSignal(std::chrono::milliseconds(0)).has_value();
    return stopping;
  };
  std::unique_ptr<processing::GraphExecutor> executor =
      executor_ == "slurm" ? processing::MakeSlurmExecutor(slurm_) : processing::MakeLocalExecutor(local_);
  // Each task's news, and after each that ends, where every stage stands.
  auto report = processing::RunGraph(
      options_, *executor,
      [&](const std::string& line) {
        std::cerr << "stage-process run: " << line << std::endl;
        if (line.find(" done: ") == std::string::npos && line.find(" failed") == std::string::npos) return;
        // The executors write status.json before they tell of a task's end.
        if (auto progress = processing::ReadGraphSummary(processing::GraphRunDir(options_.take_dir)); progress.ok()) {
          std::cerr << "stage-process run: progress: " << ProgressWords(*progress) << std::endl;
        }
      },
      cancelled);
  if (!report.ok()) return ReportFatal(kProgram, report.status());
  std::cout << (json_ ? processing::GraphReportJson(*report) + "\n" : processing::FormatGraphReport(*report));
  return report->ok() ? 0 : 2;
}

int GraphCommands::RunTask(const StageCommand& stage_command) {
  auto plan = processing::ReadPlan(run_dir_);
  if (!plan.ok()) return ReportFatal(kProgram, plan.status());
  if (task_index_ < 0 || task_index_ >= static_cast<int>(plan->tasks.size())) {
    return ReportFatal(kProgram, absl::InvalidArgumentError(
                                     absl::StrCat("--task ", task_index_, " is not in ", run_dir_, "/plan.json")));
  }
  const processing::GraphTask& task = plan->tasks[task_index_];
  const std::string name = plan->TaskName(task);
  if (!run_id_.empty() && run_id_ != plan->run_id) {
    return ReportFatal(kProgram, absl::FailedPreconditionError(
                                     absl::StrCat(name, " of run ", run_id_, ", but ", run_dir_, "/plan.json is run ",
                                                  plan->run_id, "'s: a job an earlier run left queued; not run")));
  }
  if (!give_up_.empty()) {
    processing::TaskStatus s;
    s.state = processing::TaskState::kFailed;
    s.attempt = attempt_;
    s.message = give_up_;
    const std::string last = LastError(processing::LogPath(*plan, task));
    if (!last.empty()) absl::StrAppend(&s.message, ": ", last);
    s.log = processing::LogPath(*plan, task);
    if (auto st = processing::WriteTaskStatus(processing::StatusPath(*plan, task), s); !st.ok()) {
      return ReportFatal(kProgram, st);
    }
    return 0;
  }
  // A test's hook (tests/processing_graph_test.cc): the first attempt of the task named here stops before its stage
  // runs and waits to be killed, so that the test kills it mid-run without racing it.
  const char* hold = std::getenv("STAGE_GRAPH_HOLD_TASK");
  const bool held = hold != nullptr && name == hold && attempt_ == 1;
  std::cerr << "stage-process task: " << name << " frames " << task.first << ":" << task.last << " attempt " << attempt_
            << " pid " << getpid() << std::endl;
  auto run = [&](const std::vector<std::string>& argv) -> absl::Status {
    if (held) {
      std::cerr << "stage-process task: held (STAGE_GRAPH_HOLD_TASK) until killed" << std::endl;
      while (true) pause();
    }
    // In this process: a second one would load the program's libraries again (about 2 s).
    const int code = stage_command(argv);
    if (code == 0) return absl::OkStatus();
    const std::string last = LastError(processing::LogPath(*plan, task));
    return absl::InternalError(
        absl::StrCat("stage-process ", argv[0], ": exit code ", code, last.empty() ? "" : ": ", last));
  };
  if (auto s = processing::RunGraphTask(*plan, task_index_, attempt_, run, run_id_); !s.ok()) {
    return ReportFatal(kProgram, s);
  }
  return 0;
}

}  // namespace stage::process
