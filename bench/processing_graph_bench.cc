// The processing graph's cost: a simulated take (24 frames by default) processed through every stage three ways, each
// on its own copy of the take: the baseline, one `stage-process STAGE` process per stage over all the frames, one after
// the other; the graph on this machine (`stage-process run`, the local executor); and the graph on a single-node Slurm
// cluster started here. Prints wall time, CPU time per stage and the graph's overhead beside the baseline, measured in
// the same run, and checks that the two graphs wrote the same bytes.
#include <sys/resource.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <thread>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "bench_util.h"
#include "slurm_cluster.h"
#include "stage/common/file_util.h"
#include "stage/common/subprocess.h"
#include "test_support.h"

namespace {

namespace fs = std::filesystem;
using stage::bench::Clock;
using stage::bench::Die;
constexpr const char* kProgram = "processing_graph_bench";
const char* kStages[] = {"mvs", "photometric", "fit", "textures", "stabilize"};

std::string Bin() { return fs::read_symlink("/proc/self/exe").parent_path().string(); }

double ChildrenCpu() {
  rusage u{};
  getrusage(RUSAGE_CHILDREN, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

struct Timed {
  double wall_s = 0, cpu_s = 0;
};

// Runs a program to its end (its output to `log`): its wall and CPU time; dies if it fails.
Timed Run(std::vector<std::string> argv, const std::string& log, const std::vector<std::string>& env = {}) {
  const double cpu0 = ChildrenCpu();
  const auto t0 = Clock::now();
  auto child =
      stage::Subprocess::Spawn({.argv = argv, .env = env, .stdout_path = log, .stderr_path = log, .append = true});
  if (!child.ok()) Die(kProgram, std::string(child.status().message()));
  const stage::ExitInfo exit = *(*child)->Wait();
  if (!exit.ok()) Die(kProgram, absl::StrCat(argv[0], " ", argv[1], ": ", exit.Describe(), "; see ", log));
  return {std::chrono::duration<double>(Clock::now() - t0).count(), ChildrenCpu() - cpu0};
}

// A take of `frames` frames captured on the simulated stage at `scale`: its directory.
std::string Capture(const std::string& root, int frames, double scale) {
  const std::string out = root + "/capture.json";
  Run({Bin() + "/stage-sim", "--run-dir", root + "/run", "--set", absl::StrCat("sim.render_scale=", scale),
       "--take-root", root + "/takes", "--", "bash", "-c",
       absl::StrCat("\"$0\" capture --frames ", frames, " --name graph-bench --json > ", out), Bin() + "/stagectl"},
      root + "/capture.log");
  const nlohmann::json take = nlohmann::json::parse(stage::ReadFileToString(out).value_or("{}"), nullptr, false);
  if (take.is_discarded() || !take.contains("dir")) Die(kProgram, "the capture printed no take; see " + out);
  return take["dir"];
}

// A fresh copy of `take` under `root`/`name`, the same directory name, no results.
std::string Copy(const std::string& take, const std::string& root, const std::string& name) {
  const std::string dir = root + "/" + name + "/" + fs::path(take).filename().string();
  fs::create_directories(fs::path(dir).parent_path());
  fs::copy(take, dir, fs::copy_options::recursive);
  fs::remove_all(dir + "/derived");
  fs::remove_all(dir + "/processing");
  return dir;
}

// Per stage, the CPU and wall seconds of a graph run's tasks (their status files).
std::map<std::string, Timed> TaskTimes(const std::string& take) {
  std::map<std::string, Timed> out;
  for (const auto& e : fs::directory_iterator(take + "/processing/status")) {
    const nlohmann::json s =
        nlohmann::json::parse(stage::ReadFileToString(e.path().string()).value_or("{}"), nullptr, false);
    const std::string task = e.path().stem().string();
    Timed& t = out[task.substr(0, task.find('.'))];
    t.cpu_s += s.value("cpu_s", 0.0);
    t.wall_s += s.value("wall_s", 0.0);
  }
  return out;
}

// The baseline: each stage once over every frame of `take`, in one process.
std::map<std::string, Timed> Baseline(const std::string& take, const std::string& calibration, const std::string& log) {
  std::map<std::string, Timed> out;
  for (const char* stage : kStages) {
    std::vector<std::string> command = {Bin() + "/stage-process", stage, "--take", take};
    const std::string name = stage;
    if (name != "fit" && name != "stabilize") command.insert(command.end(), {"--calibration", calibration});
    if (name == "textures") command.push_back("--size=512");
    out[stage] = Run(command, log);
  }
  return out;
}

// The two graphs' outputs, file by file: the same bytes, or the benchmark fails.
void CompareOutputs(const std::string& local, const std::string& slurm) {
  const auto a = stage::testing::FilesUnder(local + "/derived"), b = stage::testing::FilesUnder(slurm + "/derived");
  size_t same = 0;
  for (const auto& [name, bytes] : a) same += b.count(name) && b.at(name) == bytes ? 1 : 0;
  std::cout << "local and Slurm outputs: " << same << " of " << a.size() << " files identical (" << b.size()
            << " from Slurm)\n";
  if (same != a.size() || a.size() != b.size()) Die(kProgram, "the two graphs' outputs differ");
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "The processing graph's cost: a simulated take through every stage as one process per stage (the "
      "baseline), through the graph on this machine, and through a single-node Slurm cluster",
      kProgram};
  int frames = 24, chunk = 4;
  double scale = 0.0625;
  std::string take, calibration = std::string(FASTAGE_SOURCE_DIR) + "/common/rigs/fastage-sim-calibration.json";
  bool no_slurm = false;
  app.add_option("--frames", frames, "Frames of the take captured for the run")->capture_default_str();
  app.add_option("--render-scale", scale, "Its render scale")->capture_default_str();
  app.add_option("--take", take, "Process this take instead of capturing one (it is copied, not changed)");
  app.add_option("--chunk-frames", chunk, "The graph's frames per task")->capture_default_str();
  app.add_flag("--no-slurm", no_slurm, "Leave out the Slurm run");
  CLI11_PARSE(app, argc, argv);

  stage::testing::TempDir root;
  if (take.empty()) {
    std::cout << "capturing a take of " << frames << " frames at render scale " << scale << " ..." << std::endl;
    take = Capture(root.path(), frames, scale);
  }
  const std::string log = root.path() + "/bench.log";

  std::map<std::string, Timed> baseline = Baseline(Copy(take, root.path(), "baseline"), calibration, log);
  Timed base_total;
  for (const auto& [stage, t] : baseline) {
    base_total.wall_s += t.wall_s;
    base_total.cpu_s += t.cpu_s;
  }
  // The graph, here and on Slurm.
  std::vector<std::string> graph = {"--calibration",       calibration,      "--with",
                                    "textures:--size=512", "--chunk-frames", std::to_string(chunk)};
  const std::string local = Copy(take, root.path(), "local");
  std::vector<std::string> run = {Bin() + "/stage-process", "run", "--take", local};
  run.insert(run.end(), graph.begin(), graph.end());
  const Timed local_total = Run(run, log);
  Timed slurm_total;
  std::string slurm;
  std::unique_ptr<stage::testing::SlurmCluster> cluster;
  if (!no_slurm) {
    cluster = std::make_unique<stage::testing::SlurmCluster>(root.path() + "/slurm");
    if (!cluster->ok()) Die(kProgram, "the Slurm cluster did not come up: " + cluster->error());
    slurm = Copy(take, root.path(), "slurm");
    run = {Bin() + "/stage-process", "run", "--take", slurm, "--executor", "slurm", "--poll-ms", "200"};
    run.insert(run.end(), graph.begin(), graph.end());
    slurm_total = Run(run, log, cluster->env());
  }
  const auto local_tasks = TaskTimes(local);
  const auto slurm_tasks = no_slurm ? std::map<std::string, Timed>{} : TaskTimes(slurm);
  std::cout << absl::StrFormat("\n%s, %d frames per task; seconds per stage (the graph's: its tasks' own CPU)\n", take,
                               chunk);
  std::cout << absl::StrFormat("%-12s %12s %12s %12s %12s\n", "stage", "baseline wall", "baseline CPU", "local CPU",
                               "slurm CPU");
  for (const char* stage : kStages) {
    std::cout << absl::StrFormat("%-12s %12.1f %12.1f %12.1f %12.1f\n", stage, baseline[stage].wall_s,
                                 baseline[stage].cpu_s, local_tasks.count(stage) ? local_tasks.at(stage).cpu_s : 0.0,
                                 slurm_tasks.count(stage) ? slurm_tasks.at(stage).cpu_s : 0.0);
  }
  std::cout << absl::StrFormat("\n%-34s %8s %8s\n", "", "wall s", "CPU s");
  std::cout << absl::StrFormat("%-34s %8.1f %8.1f\n", "baseline (one process per stage)", base_total.wall_s,
                               base_total.cpu_s);
  std::cout << absl::StrFormat("%-34s %8.1f %8.1f   overhead %+.1f s wall (%+.0f %%)\n", "graph, local executor",
                               local_total.wall_s, local_total.cpu_s, local_total.wall_s - base_total.wall_s,
                               100 * (local_total.wall_s / base_total.wall_s - 1));
  if (!no_slurm) {
    std::cout << absl::StrFormat(
        "%-34s %8.1f %8s   overhead %+.1f s wall (%+.0f %%) beside the local graph %+.1f s\n",
        "graph, slurm executor (1 node)", slurm_total.wall_s, "-", slurm_total.wall_s - base_total.wall_s,
        100 * (slurm_total.wall_s / base_total.wall_s - 1), slurm_total.wall_s - local_total.wall_s);
    CompareOutputs(local, slurm);
  }
  return 0;
}
