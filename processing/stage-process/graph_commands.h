// `stage-process run` (the processing graph over a take, docs/processing.md#the-graph), `stage-process status` (where
// a take's run stands) and `stage-process task` (one of its tasks: what the executors start, here or on a Slurm node).
#pragma once

#include <CLI/CLI.hpp>
#include <functional>
#include <string>
#include <vector>

#include "stage/processing/graph_executor.h"

namespace stage::process {

class GraphCommands {
 public:
  void Add(CLI::App& parent);
  // True when one of them was given on the command line.
  bool Parsed() const;
  // Runs a stage's command line (["mvs", "--take", ...]) in this process: its exit code. A task's stage.
  using StageCommand = std::function<int(const std::vector<std::string>& args)>;
  int Run(const StageCommand& stage_command);

 private:
  void AddRun(CLI::App& parent);
  void AddExecutorOptions();  // run's --executor local and slurm options
  void AddStatusAndTask(CLI::App& parent);
  int RunGraph();
  int Status();
  int RunTask(const StageCommand& stage_command);
  // Fills options_ and the executor's from the flags; an error names the flag.
  absl::Status Collect();

  CLI::App* run_ = nullptr;
  CLI::App* task_ = nullptr;
  CLI::App* status_ = nullptr;
  processing::GraphOptions options_;
  std::string stages_, frames_ = "0:", executor_ = "local";
  std::vector<std::string> with_, cpus_, mem_;
  processing::LocalExecutorOptions local_;
  processing::SlurmOptions slurm_;
  bool dry_run_ = false, json_ = false;
  // task
  std::string run_dir_, give_up_, run_id_;
  int task_index_ = -1, attempt_ = 1;
};

}  // namespace stage::process
