// A fixture for suites that run the full simulated stage (stage-sim) as a user does: StartStage() brings it up and
// reads its endpoint file; TearDown() takes it down and makes sure no process it started is left.
#pragma once

#include <google/protobuf/util/json_util.h>
#include <signal.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "gtest/gtest.h"
#include "stage/common/subprocess.h"
#include "stage/v1/sim.pb.h"
#include "test_support.h"

namespace stage::testing {

inline bool Alive(pid_t pid) { return kill(pid, 0) == 0; }

// The rig overrides of suites about the control plane (takes, faults, the ledger), before their own: small images of
// a head that holds still. A camera node then computes its subject's light transport once a take instead of once a
// frame (about 1.7 s of both cores a frame on the full rig, most of such a suite's time), and nothing these suites
// assert depends on the subject moving.
inline std::vector<std::string> ControlPlaneScene(std::vector<std::string> more = {}) {
  std::vector<std::string> args = {"--set", "sim.render_scale=0.02", "--set", "sim.subject.performance=still"};
  for (auto& m : more) args.push_back(std::move(m));
  return args;
}

// One integer column of a frame file (e.g. "/slot", "/pattern"), read by HDF5's own h5dump; empty (with a test
// failure) when h5dump cannot read it.
inline std::vector<int64_t> ReadH5Column(const std::string& path, const std::string& dataset) {
  CommandResult dump = RunCommand({"/usr/bin/h5dump", "-d", dataset, "-y", "-w", "0", path}, std::chrono::seconds(30));
  EXPECT_EQ(dump.exit.exit_code, 0) << path << ": " << dump.err;
  std::vector<int64_t> values;
  const size_t data = dump.out.find("DATA {");  // DATA { 19, 57, ... } (-y: without indexes)
  if (data == std::string::npos) return values;
  const size_t close = dump.out.find('}', data);
  std::string list = dump.out.substr(data + 6, close == std::string::npos ? std::string::npos : close - data - 6);
  for (char& c : list) {
    if (c == ',') c = ' ';
  }
  std::istringstream in(list);
  int64_t v;
  while (in >> v) values.push_back(v);
  return values;
}

class SimulatedStageTest : public ::testing::Test {
 protected:
  void StartStage(std::vector<std::string> extra = {}) {
    std::vector<std::string> argv = {BinDir() + "/stage-sim", "--run-dir", run_dir_.path(), "--grace-ms", "1500"};
    for (auto& a : extra) argv.push_back(std::move(a));
    auto sim = Subprocess::Spawn({.argv = argv, .stderr_path = run_dir_.path() + "/stage-sim.log"});
    ASSERT_TRUE(sim.ok()) << sim.status();
    sim_ = std::move(*sim);
    // stage-sim writes the endpoint file once every node is up.
    std::string path = run_dir_.path() + "/endpoints.json";
    auto deadline = std::chrono::steady_clock::now() + startup_deadline_;
    while (!std::filesystem::exists(path)) {
      ASSERT_FALSE(sim_->Poll().has_value()) << "stage-sim exited: " << ReadFile(run_dir_.path() + "/stage-sim.log");
      ASSERT_LT(std::chrono::steady_clock::now(), deadline) << ReadFile(run_dir_.path() + "/stage-sim.log");
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    google::protobuf::util::JsonParseOptions options;
    ASSERT_TRUE(google::protobuf::util::JsonStringToMessage(ReadFile(path), &endpoints_, options).ok());
    for (const auto& p : endpoints_.processes()) pids_.push_back(p.pid());
  }

  void TearDown() override {
    if (sim_ && !sim_->exited()) sim_->Terminate(std::chrono::seconds(10));
    // stage-sim's children die with it (PR_SET_PDEATHSIG); this is only a backstop for a failed test.
    for (pid_t pid : pids_) {
      if (Alive(pid)) kill(pid, SIGKILL);
    }
  }

  nlohmann::json StatusJson() {
    CommandResult r =
        RunCommand({"stagectl", "--endpoints", Endpoints(), "status", "--json"}, std::chrono::seconds(20));
    EXPECT_FALSE(r.timed_out);
    return nlohmann::json::parse(r.out);
  }

  // Why a capture did not end complete, for a failure message: the take's outcome, its hint and every alignment
  // check that failed (from `stagectl capture --json`), then the end of stage-sim's log. These come first because a
  // test runner that keeps only part of a long output would otherwise cut them from the middle of the JSON.
  std::string CaptureVerdict(const CommandResult& capture) {
    std::ostringstream out;
    const nlohmann::json take = nlohmann::json::parse(capture.out, nullptr, /*allow_exceptions=*/false);
    if (take.is_object()) {
      out << "outcome " << take.value("outcome", "?") << "; hint: " << take.value("hint", "(none)") << "\n";
      if (take.contains("alignment")) {
        for (const auto& a : take["alignment"]) {
          if (!a.value("ok", false)) out << "alignment " << a.dump() << "\n";
        }
      }
    } else {
      out << "no take summary on stdout\n";
    }
    // The nodes' warnings and errors (a light node's watchdog, a camera that fell behind), but not the
    // controller's health checks of nodes still starting.
    std::vector<std::string> warnings;
    std::error_code ec;
    for (const auto& file : std::filesystem::directory_iterator(run_dir_.path() + "/logs", ec)) {
      std::istringstream lines(ReadFile(file.path().string()));
      for (std::string line; std::getline(lines, line);) {
        const bool bad = line.find(" warning ") != std::string::npos || line.find(" error ") != std::string::npos;
        if (bad && line.find("is unreachable") == std::string::npos) warnings.push_back(line.substr(0, 300));
      }
    }
    // In time order (each line starts with its time), the latest 40: those nearest the take's end.
    std::sort(warnings.begin(), warnings.end());
    const size_t from = warnings.size() > 40 ? warnings.size() - 40 : 0;
    out << warnings.size() << " warning(s) and error(s) in the nodes' logs" << (from > 0 ? ", the last 40" : "")
        << ":\n";
    for (size_t k = from; k < warnings.size(); ++k) out << "  " << warnings[k] << "\n";
    const std::string log = ReadFile(run_dir_.path() + "/stage-sim.log");
    out << "stage-sim.log (last 4000 characters):\n" << log.substr(log.size() > 4000 ? log.size() - 4000 : 0) << "\n";
    out << "stderr:\n" << capture.err;
    return out.str();
  }

  // The running stage's endpoint file, which stagectl is pointed at.
  std::string Endpoints() const { return run_dir_.path() + "/endpoints.json"; }

  // stagectl on the running stage, waited for: within `timeout`, or the suite's stagectl_timeout_.
  CommandResult Stagectl(std::vector<std::string> args) { return Stagectl(std::move(args), stagectl_timeout_); }
  CommandResult Stagectl(std::vector<std::string> args, std::chrono::seconds timeout) {
    args.insert(args.begin(), {"stagectl", "--endpoints", Endpoints()});
    return RunCommand(args, timeout);
  }

  // stagectl in the background; its stdout and stderr go to <run dir>/<name>.out and .err.
  std::unique_ptr<Subprocess> SpawnStagectl(std::vector<std::string> args, const std::string& name) {
    args.insert(args.begin(), {BinDir() + "/stagectl", "--endpoints", Endpoints()});
    auto p = Subprocess::Spawn({.argv = args,
                                .stdout_path = run_dir_.path() + "/" + name + ".out",
                                .stderr_path = run_dir_.path() + "/" + name + ".err"});
    EXPECT_TRUE(p.ok()) << p.status();
    return p.ok() ? std::move(*p) : nullptr;
  }

  // The session's state in words ("capturing"), from `stagectl status --json` (which carries the enum's name).
  std::string SessionState() {
    std::string name = StatusJson()["session_state"];
    const std::string prefix = "SESSION_STATE_";
    if (name.rfind(prefix, 0) == 0) name = name.substr(prefix.size());
    for (char& c : name) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return name;
  }

  // Polls the session state (every 200 ms) until it is `want`; false when `timeout` passed first.
  bool WaitForSession(const std::string& want, std::chrono::seconds timeout) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (std::chrono::steady_clock::now() < deadline) {
      if (SessionState() == want) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
    return false;
  }

  // How long Stagectl(args) waits for stagectl. Suites whose commands are all quick lower it.
  std::chrono::seconds stagectl_timeout_{300};
  // How long StartStage waits for the stage to come up. Suites on a loaded machine raise it.
  std::chrono::seconds startup_deadline_{90};
  TempDir run_dir_;
  std::unique_ptr<Subprocess> sim_;
  v1::SimEndpoints endpoints_;
  std::vector<pid_t> pids_;
};

}  // namespace stage::testing
