// The demo's takes on a busy machine. Both cores run busy loops of other work, and the stage's own processes (camera
// nodes, light nodes, and stage-sim, which holds the simulated world) are stopped and continued (SIGSTOP / SIGCONT)
// for longer than any drain, as a starved machine stops them. In the lockstep world nothing may depend on wall-clock
// time: a take waits for the devices that work on it, so every take stays COMPLETE with every frame stored, and no
// light node takes a stop of its own for the controller's silence.
#include <signal.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <nlohmann/json.hpp>
#include <random>
#include <set>
#include <thread>

#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "test_support.h"

namespace stage::testing {
namespace {

// Other work on every core: a busy loop per core, twice over (the test's own children, ended by pid).
class BusyLoops {
 public:
  explicit BusyLoops(int per_core) {
    const int n = per_core * static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
    for (int i = 0; i < n; ++i) {
      auto p = Subprocess::Spawn({.argv = {"/bin/sh", "-c", "while :; do :; done"}});
      EXPECT_TRUE(p.ok()) << p.status();
      if (p.ok()) loops_.push_back(std::move(*p));
    }
  }
  ~BusyLoops() {
    for (auto& p : loops_) p->Terminate(std::chrono::milliseconds(500));
  }
  size_t size() const { return loops_.size(); }

 private:
  std::vector<std::unique_ptr<Subprocess>> loops_;
};

// Stops a few of the given processes (chosen at random, seeded) for `stop`, continues them, lets everything run for
// `run`, and again, until destroyed; every process it stopped is continued before it returns.
class Stopper {
 public:
  Stopper(std::vector<pid_t> victims, size_t at_once, std::chrono::milliseconds stop, std::chrono::milliseconds run)
      : victims_(std::move(victims)) {
    thread_ = std::thread([this, at_once, stop, run] { Run(at_once, stop, run); });
  }
  ~Stopper() { Stop(); }
  void Stop() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      done_ = true;
    }
    wake_.notify_all();
    if (thread_.joinable()) thread_.join();
  }
  // Stops made so far.
  int stops() const { return stops_.load(); }

 private:
  void Run(size_t at_once, std::chrono::milliseconds stop, std::chrono::milliseconds run) {
    std::mt19937 random(25);
    std::unique_lock<std::mutex> lock(mutex_);
    while (!done_) {
      std::vector<pid_t> pick = victims_;
      std::shuffle(pick.begin(), pick.end(), random);
      pick.resize(std::min(at_once, pick.size()));
      for (pid_t pid : pick) {
        if (kill(pid, SIGSTOP) == 0) ++stops_;
      }
      wake_.wait_for(lock, stop, [this] { return done_; });
      for (pid_t pid : pick) kill(pid, SIGCONT);
      wake_.wait_for(lock, run, [this] { return done_; });
    }
  }

  std::vector<pid_t> victims_;
  std::mutex mutex_;
  std::condition_variable wake_;
  bool done_ = false;
  std::atomic<int> stops_{0};
  std::thread thread_;
};

class LoadTest : public SimulatedStageTest {
 protected:
  LoadTest() { startup_deadline_ = std::chrono::seconds(600); }
};

// The demo's photometric take (27 cameras, each precomputing the head's pose on first use; at render scale 0.0625, half
// the demo's, which halves the test's time and keeps every camera rendering through the stops) with
// both cores busy and, throughout, three of the stage's device processes at a time stopped for 8 s (then 4 s of all
// running): longer than the controller's drain and the grace it used to give before it called every late frame a
// missed trigger, and longer than a keepalive's timeout.
TEST_F(LoadTest, TheDemosPhotometricTakeStaysCompleteOnABusyMachineWithItsNodesStoppedAndContinued) {
  TempDir root;
  BusyLoops busy(2);
  ASSERT_GE(busy.size(), 2u);
  ASSERT_NO_FATAL_FAILURE(StartStage({"--set", "sim.render_scale=0.0625", "--take-root", root.path()}));
  std::vector<pid_t> devices;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() == v1::NODE_KIND_CAMERA || p.kind() == v1::NODE_KIND_LIGHT) devices.push_back(p.pid());
  }
  devices.push_back(endpoints_.stage_sim_pid());  // the simulated world: its slot clock stands while it is stopped
  Stopper stopper(devices, 3, std::chrono::seconds(8), std::chrono::seconds(4));

  CommandResult capture =
      Stagectl({"capture", "--frames", "1", "--name", "photometric", "--json"}, std::chrono::seconds(900));
  stopper.Stop();
  ASSERT_FALSE(capture.timed_out) << capture.err;
  EXPECT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  ASSERT_FALSE(capture.out.empty()) << capture.err;
  EXPECT_GE(stopper.stops(), 6) << "the take ended before the stops could test it";
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE") << take.dump(2) << "\n" << capture.err;
  EXPECT_EQ(take["total"]["expected"], "138");
  EXPECT_EQ(take["total"]["stored"], "138");
  EXPECT_EQ(take["hint"], "");
}

// Half of the demo's one-second take (456 slots, 1656 frames at render scale 0.02; the head held still, so that the
// busy loops and the stops, not the rendering, make the load; on this machine it still lasts over a minute, several
// rounds of stops) on busy cores, its devices stopped and continued: COMPLETE, every frame stored.
TEST_F(LoadTest, AHalfSecondTakeOfTheDemosSceneStaysCompleteOnABusyMachineWithItsNodesStoppedAndContinued) {
  TempDir root;
  BusyLoops busy(2);
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  std::vector<pid_t> devices;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() == v1::NODE_KIND_CAMERA || p.kind() == v1::NODE_KIND_LIGHT) devices.push_back(p.pid());
  }
  devices.push_back(endpoints_.stage_sim_pid());
  Stopper stopper(devices, 3, std::chrono::seconds(8), std::chrono::seconds(4));
  CommandResult capture =
      Stagectl({"capture", "--seconds", "0.5", "--name", "demo", "--json"}, std::chrono::seconds(900));
  stopper.Stop();
  ASSERT_FALSE(capture.timed_out) << capture.err;
  EXPECT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  ASSERT_FALSE(capture.out.empty()) << capture.err;
  EXPECT_GE(stopper.stops(), 6);
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE") << take.dump(2) << "\n" << capture.err;
  EXPECT_EQ(take["total"]["expected"], "1656");
  EXPECT_EQ(take["total"]["stored"], "1656");
}

}  // namespace
}  // namespace stage::testing
