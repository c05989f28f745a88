// The processing graph over a take of the simulated stage: through the stage's worker (stagectl process, the local
// executor), and through a real single-node Slurm cluster (stage-process run --executor slurm) with a task killed
// mid-run and retried; the same bytes either way. A re-run does nothing; a changed flag redoes its stage and what
// reads it; a stage that fails is reported with its log and what waits for it is cancelled.
#include <signal.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "slurm_cluster.h"
#include "test_support.h"

namespace stage::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

using ProcessingGraphTest = SimulatedStageTest;

const std::string kCalibration = std::string(FASTAGE_SOURCE_DIR) + "/common/rigs/fastage-sim-calibration.json";

// The tasks a run's report says ran, by name.
std::vector<std::string> TasksRun(const nlohmann::json& report) {
  std::vector<std::string> out;
  for (const auto& t : report["tasks"]) {
    if (t["ran"]) out.push_back(t["task"]);
  }
  return out;
}

// Waits for the task's status file to say it runs its attempt 1: its pid, or 0 after `timeout`.
pid_t WaitForRunning(const std::string& status_file, std::chrono::seconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (fs::exists(status_file)) {
      const nlohmann::json s = nlohmann::json::parse(ReadFile(status_file), nullptr, false);
      if (!s.is_discarded() && s["state"] == "running" && s["attempt"] == 1) return s["pid"].get<pid_t>();
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return 0;
}

TEST_F(ProcessingGraphTest, TheWorkerAndSlurmMakeTheSameBytesAndOnlyWhatIsStaleRuns) {
  TempDir root, copies;
  ASSERT_NO_FATAL_FAILURE(StartStage({"--set", "sim.render_scale=0.0625", "--take-root", root.path()}));
  CommandResult capture = Stagectl({"capture", "--frames", "2", "--json"}, std::chrono::seconds(300));
  ASSERT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  const std::string id = take["take_id"], dir = take["dir"];
  // The copy Slurm processes, as it was recorded (the same directory name: results name their take).
  const std::string copy = copies.path() + "/" + id;
  fs::copy(dir, copy, fs::copy_options::recursive);

  // Through the stage's worker: every stage, two frames, a task per frame.
  const std::vector<std::string> graph = {"--calibration",       kCalibration,     "--with",
                                          "textures:--size=128", "--chunk-frames", "1"};
  std::vector<std::string> process = {"process", id, "--json"};
  process.insert(process.end(), graph.begin(), graph.end());
  CommandResult worker = Stagectl(process, std::chrono::seconds(900));
  ASSERT_EQ(worker.exit.exit_code, 0) << worker.err;
  const nlohmann::json done = nlohmann::json::parse(worker.out);
  EXPECT_EQ(done["output_dir"], dir + "/processing");
  EXPECT_EQ(done["frames_done"], done["frames_total"]);
  EXPECT_EQ(done["frames_total"], "9");  // mvs, photometric, fit, textures: 2 frames each; stabilize: 1
  EXPECT_THAT(worker.err, HasSubstr("photometric.1 done"));
  // The catalog says per stage where the take's processing stands (the console's Takes page shows it).
  CommandResult takes = Stagectl({"takes", "--json"}, std::chrono::seconds(30));
  ASSERT_EQ(takes.exit.exit_code, 0) << takes.err;
  nlohmann::json processing;
  const nlohmann::json listed = nlohmann::json::parse(takes.out);
  for (const auto& t : listed["takes"]) {
    if (t["id"] == id) processing = t["processing"];
  }
  ASSERT_EQ(processing.size(), 5u) << takes.out;
  for (const auto& s : processing) EXPECT_EQ(s["state"], "STAGE_PROCESSING_STATE_DONE") << s.dump();
  EXPECT_EQ(processing[0]["stage"], "PROCESSING_STAGE_MVS");
  CommandResult table = Stagectl({"takes"}, std::chrono::seconds(30));
  EXPECT_THAT(table.out, HasSubstr("processing: mvs done 2/2, photometric done 2/2, fit done 2/2"));
  // Again: everything is up to date.
  CommandResult again = Stagectl(process, std::chrono::seconds(300));
  ASSERT_EQ(again.exit.exit_code, 0) << again.err;
  EXPECT_EQ(nlohmann::json::parse(again.out)["message"],
            "take " + id + ": every output asked for is up to date: nothing to do");
  sim_->Terminate(std::chrono::seconds(10));  // the rest needs no stage

  // Through Slurm, with the first attempt of photometric.1 held until the test kills it: retried, and the same bytes.
  SlurmCluster cluster(root.path() + "/slurm");
  ASSERT_TRUE(cluster.ok()) << cluster.error();
  std::vector<std::string> slurm_env = cluster.env();
  slurm_env.push_back("STAGE_GRAPH_HOLD_TASK=photometric.1");
  std::vector<std::string> run = {
      BinDir() + "/stage-process", "run", "--take", copy, "--executor", "slurm", "--poll-ms", "100", "--json"};
  run.insert(run.end(), graph.begin(), graph.end());
  auto slurm_run = Subprocess::Spawn({.argv = run,
                                      .env = slurm_env,
                                      .stdout_path = copies.path() + "/slurm.out",
                                      .stderr_path = copies.path() + "/slurm.err"});
  ASSERT_TRUE(slurm_run.ok()) << slurm_run.status();
  const pid_t held = WaitForRunning(copy + "/processing/status/photometric.1.json", std::chrono::seconds(600));
  ASSERT_GT(held, 0) << ReadFile(copies.path() + "/slurm.err") << cluster.Logs();
  ASSERT_EQ(kill(held, SIGKILL), 0);
  const std::optional<ExitInfo> ended = (*slurm_run)->Wait(std::chrono::seconds(900));
  ASSERT_TRUE(ended.has_value()) << ReadFile(copies.path() + "/slurm.err");
  const std::string slurm_err = ReadFile(copies.path() + "/slurm.err");
  ASSERT_TRUE(ended->ok()) << ended->Describe() << slurm_err;
  EXPECT_THAT(slurm_err, HasSubstr("probe: "));
  EXPECT_THAT(slurm_err, HasSubstr("photometric.1: attempt 2 (a retry)"));
  const nlohmann::json report = nlohmann::json::parse(ReadFile(copies.path() + "/slurm.out"));
  EXPECT_EQ(report["executor"], "slurm");
  EXPECT_TRUE(report["ok"]) << report.dump(2);
  for (const auto& t : report["tasks"]) {
    if (t["task"] == "photometric.1") {
      EXPECT_EQ(t["attempts"], 2) << t.dump();
    }
  }
  EXPECT_THAT(ReadFile(copy + "/processing/logs/photometric.1.log"), HasSubstr("held (STAGE_GRAPH_HOLD_TASK)"));
  const auto local = FilesUnder(dir + "/derived"), slurm = FilesUnder(copy + "/derived");
  EXPECT_GT(local.size(), 100u);
  EXPECT_EQ(local.size(), slurm.size());
  for (const auto& [name, bytes] : local) {
    ASSERT_EQ(slurm.count(name), 1u) << name << " is missing from the Slurm run's outputs";
    EXPECT_TRUE(bytes == slurm.at(name)) << name << " differs between the worker's run and Slurm's";
  }
  EXPECT_EQ(local.count("mvs/frame-000001/manifest.json"), 1u);
  EXPECT_EQ(local.count("textures-stable/manifest.json"), 1u);

  // A changed flag of the textures redoes them and the stabilization, nothing else.
  std::vector<std::string> changed = {
      "stage-process",  "run", "--take", copy, "--json", "--calibration", kCalibration, "--with", "textures:--size=64",
      "--chunk-frames", "1"};
  CommandResult redo = RunCommand(changed, std::chrono::seconds(600));
  ASSERT_EQ(redo.exit.exit_code, 0) << redo.err;
  const nlohmann::json redone = nlohmann::json::parse(redo.out);
  EXPECT_EQ(TasksRun(redone), (std::vector<std::string>{"textures.0", "textures.1", "stabilize.0"}));
  EXPECT_EQ(redone["tasks"][6]["why"], "stale: flags changed");
  EXPECT_EQ(ReadFile(copy + "/derived/fit/frame-000001/mesh.obj"), local.at("fit/frame-000001/mesh.obj"));
  EXPECT_NE(ReadFile(copy + "/derived/textures/frame-000001/albedo.exr"), local.at("textures/frame-000001/albedo.exr"));
  CommandResult nothing = RunCommand(changed, std::chrono::seconds(300));
  ASSERT_EQ(nothing.exit.exit_code, 0) << nothing.err;
  EXPECT_TRUE(nlohmann::json::parse(nothing.out)["nothing_to_do"]);

  // A fit that fails (a template that is not there), twice: reported with its log, what reads it cancelled by Slurm,
  // what was in place left there.
  std::vector<std::string> failing = {BinDir() + "/stage-process",
                                      "run",
                                      "--take",
                                      copy,
                                      "--executor",
                                      "slurm",
                                      "--poll-ms",
                                      "100",
                                      "--json",
                                      "--calibration",
                                      kCalibration,
                                      "--with",
                                      "textures:--size=64",
                                      "--chunk-frames",
                                      "1",
                                      "--with",
                                      "fit:--template=" + root.path() + "/no-template.obj"};
  CommandResult fail = RunCommand(failing, std::chrono::seconds(600), cluster.env());
  EXPECT_EQ(fail.exit.exit_code, 2) << fail.err;
  const nlohmann::json failed = nlohmann::json::parse(fail.out);
  EXPECT_FALSE(failed["ok"]);
  EXPECT_EQ(TasksRun(failed), (std::vector<std::string>{"fit.0", "textures.0", "textures.1", "stabilize.0"}));
  ASSERT_EQ(failed["failures"].size(), 4u) << failed.dump(2);
  EXPECT_EQ(failed["failures"][0]["task"], "fit.0");
  EXPECT_EQ(failed["failures"][0]["state"], "failed");
  EXPECT_THAT(failed["failures"][0]["message"].get<std::string>(), HasSubstr("no-template.obj"));
  EXPECT_EQ(failed["failures"][0]["log"], copy + "/processing/logs/fit.0.log");
  EXPECT_THAT(ReadFile(copy + "/processing/logs/fit.0.log"), HasSubstr("attempt 2 failed"));
  for (int i = 1; i < 4; ++i) {
    EXPECT_EQ(failed["failures"][i]["state"], "cancelled") << failed["failures"][i].dump();
    EXPECT_THAT(failed["failures"][i]["message"].get<std::string>(), HasSubstr("Slurm ended its job"));
  }
  EXPECT_EQ(ReadFile(copy + "/derived/fit/frame-000001/mesh.obj"), local.at("fit/frame-000001/mesh.obj"));
  const nlohmann::json status = nlohmann::json::parse(ReadFile(copy + "/processing/status.json"));
  EXPECT_EQ(status["stages"][2]["state"], "failed");
  EXPECT_EQ(status["stages"][3]["state"], "cancelled");
}

// A take the cluster's jobs cannot read is refused before anything is submitted, saying so.
TEST(ProcessingGraphSlurmTest, ATakeTheNodesCannotReadIsRefusedByTheProbe) {
  if (getuid() != 0) GTEST_SKIP() << "the probe's job runs as another user (sbatch --uid), which needs root";
  TempDir root;
  SlurmCluster cluster(root.path() + "/slurm");
  ASSERT_TRUE(cluster.ok()) << cluster.error();
  const std::string take = root.path() + "/take";
  fs::create_directories(take + "/cameras");
  root.Write("take/take.json", R"({"summary": {"frames": "2"}})");
  // The jobs run as a user who cannot read the take (the test's directory is its owner's alone), as on a node that
  // does not mount it.
  CommandResult r = RunCommand(
      {"stage-process", "run", "--take", take, "--executor", "slurm", "--poll-ms", "100", "--sbatch-arg=--uid=nobody"},
      std::chrono::seconds(300), cluster.env());
  EXPECT_EQ(r.exit.exit_code, 2) << r.err;
  EXPECT_THAT(r.err, HasSubstr("is not readable, or its processing directory not writable, from the compute nodes"));
  EXPECT_THAT(r.err, HasSubstr(take + "/processing/logs/probe.log"));
}

}  // namespace
}  // namespace stage::testing
