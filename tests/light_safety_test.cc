// Light safety on the simulated stage: the emergency stop darkens every light node before it is acknowledged and
// stays latched until reset; a controller killed mid-take leaves no light on (each node's heartbeat watchdog). The
// world's record of the light (SimWorld.Exposure: what each LED emitted over a window) is the judge.
#include <grpcpp/grpcpp.h>
#include <signal.h>

#include <chrono>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/clock.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "stage/v1/sim.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;
using namespace std::chrono_literals;

int64_t MonotonicNs() { return RealClock(RealClock::Kind::kMonotonic).NowNs(); }

class LightSafetyTest : public SimulatedStageTest {
 protected:
  LightSafetyTest() { stagectl_timeout_ = 60s; }

  std::unique_ptr<Subprocess> SpawnCapture(int frames) {
    return SpawnStagectl({"capture", "--frames", std::to_string(frames), "--json"}, "capture");
  }

  // Total light every LED emitted over [t0, t1] (monotonic ns: the real-time world's clock), both emitters.
  double LightBetween(int64_t t0, int64_t t1) {
    auto world = v1::SimWorld::NewStub(MakeChannel(endpoints_.world()));
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + 20s);
    v1::ExposureRequest request;
    request.set_t0_ns(t0);
    request.set_t1_ns(t1);
    v1::ExposureLevels levels;
    grpc::Status s = world->Exposure(&context, request, &levels);
    EXPECT_TRUE(s.ok()) << s.error_message() << " (window " << t0 << ".." << t1 << ")";
    EXPECT_TRUE(levels.error().empty()) << levels.error();
    double sum = 0;
    for (float v : levels.cross()) sum += v;
    for (float v : levels.parallel()) sum += v;
    return sum;
  }

  std::vector<v1::LightStats> LightStats() {
    std::vector<v1::LightStats> all;
    for (const auto& p : endpoints_.processes()) {
      if (p.kind() != v1::NODE_KIND_LIGHT) continue;
      auto stub = v1::LightNode::NewStub(MakeChannel(p.address()));
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + 5s);
      v1::LightStats stats;
      EXPECT_TRUE(stub->GetStats(&context, v1::GetLightStatsRequest(), &stats).ok()) << p.id();
      all.push_back(stats);
    }
    return all;
  }
};

TEST_F(LightSafetyTest, TheEmergencyStopDarkensEveryLightBeforeItAnswersAndLatchesUntilReset) {
  TempDir root;
  // A real-time world: its clock is the monotonic clock, so "after the acknowledgement" has one meaning everywhere.
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--world", "realtime", "--take-root", root.path()})));
  auto capture = SpawnCapture(240);  // 10 s of stage
  ASSERT_NE(capture, nullptr);
  ASSERT_TRUE(WaitForSession("capturing", 120s)) << ReadFile(run_dir_.path() + "/capture.err");
  std::this_thread::sleep_for(500ms);

  auto controller = v1::StageController::NewStub(MakeChannel(endpoints_.controller()));
  v1::EmergencyStopRequest request;
  request.set_reason("test");
  v1::EmergencyStopReply reply;
  grpc::ClientContext context;
  const int64_t sent = MonotonicNs();
  grpc::Status s = controller->EmergencyStop(&context, request, &reply);
  const int64_t acknowledged = MonotonicNs();
  ASSERT_TRUE(s.ok()) << s.error_message();
  std::printf("emergency stop: RPC to the last light node confirmed dark %.2f ms (controller's count %.2f ms)\n",
              (acknowledged - sent) / 1e6, reply.elapsed_ms());
  RecordProperty("estop_ms", std::to_string((acknowledged - sent) / 1e6));
  EXPECT_TRUE(reply.latched());
  EXPECT_TRUE(reply.all_dark());
  ASSERT_EQ(reply.nodes_size(), 6);
  for (const auto& n : reply.nodes()) {
    std::printf("  %s dark after %.2f ms\n", n.node_id().c_str(), n.ms());
    EXPECT_TRUE(n.dark()) << n.node_id() << ": " << n.error();
    EXPECT_LE(n.ms(), reply.elapsed_ms());
  }
  // Lit up to the stop, dark from the acknowledgement on, every emitter of every node. The window is as long as the
  // world can vouch for: the take is aborted after the answer, at a frame boundary, and the bus's last edge promises
  // one more slot (1.1 ms) of the light it set.
  EXPECT_GT(LightBetween(sent - 50'000'000, sent - 5'000'000), 0.0);
  EXPECT_EQ(LightBetween(acknowledged, acknowledged + 1'000'000), 0.0);
  for (const v1::LightStats& stats : LightStats()) {
    EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_BLACKOUT);
    EXPECT_EQ(stats.blackout_reason(), "emergency stop: test");
  }
  // The take was aborted; the stop is latched: in the status, and nothing arms.
  auto exit = capture->Wait(120s);
  ASSERT_TRUE(exit.has_value());
  EXPECT_NE(exit->exit_code, 0);
  nlohmann::json status = StatusJson();
  EXPECT_EQ(status["estop_latched"], true);
  EXPECT_EQ(status["estop_reason"], "emergency stop: test");
  CommandResult refused = Stagectl({"capture", "--frames", "2"});
  EXPECT_EQ(refused.exit.exit_code, 2) << refused.err;
  EXPECT_THAT(refused.err, HasSubstr("the emergency stop is latched (emergency stop: test)"));
  // stagectl estop again: still dark, every node confirms; then reset, and a take runs.
  CommandResult again = Stagectl({"estop", "--reason", "again"});
  EXPECT_EQ(again.exit.exit_code, 0) << again.err;
  EXPECT_THAT(again.out, HasSubstr("emergency stop latched: 6 of 6 light nodes confirmed dark"));
  CommandResult reset = Stagectl({"estop", "--reset"});
  EXPECT_EQ(reset.exit.exit_code, 0) << reset.err;
  EXPECT_THAT(reset.out, HasSubstr("6 of 6 light nodes out of blackout"));
  EXPECT_EQ(StatusJson()["estop_latched"], false);
  for (const v1::LightStats& stats : LightStats()) EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_IDLE);
  // A take arms and runs again (a real-time world on a busy machine may lose frames: COMPLETE or DEGRADED).
  CommandResult take = Stagectl({"capture", "--frames", "2"}, 120s);
  EXPECT_FALSE(take.timed_out) << take.err;  // stopped by the test: its exit code says nothing
  EXPECT_THAT(take.exit.exit_code, ::testing::AnyOf(0, 4)) << take.out << take.err;
}

TEST_F(LightSafetyTest, AControllerKilledMidTakeLeavesEveryLightDark) {
  TempDir root;
  // A real-time world: its clock is the monotonic clock, so "after the acknowledgement" has one meaning everywhere.
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--world", "realtime", "--take-root", root.path()})));
  auto capture = SpawnCapture(480);  // 20 s of stage: the bus runs on after the controller dies
  ASSERT_NE(capture, nullptr);
  ASSERT_TRUE(WaitForSession("capturing", 120s)) << ReadFile(run_dir_.path() + "/capture.err");
  std::this_thread::sleep_for(500ms);
  pid_t controller = 0;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() == v1::NODE_KIND_CONTROLLER) controller = p.pid();
  }
  ASSERT_GT(controller, 0);
  const int64_t killed = MonotonicNs();
  EXPECT_GT(LightBetween(killed - 50'000'000, killed - 5'000'000), 0.0);  // lit while the take ran
  ASSERT_EQ(kill(controller, SIGKILL), 0);
  // Each node's watchdog (1 s without a heartbeat) blacks it out.
  std::vector<v1::LightStats> stats;
  const auto deadline = std::chrono::steady_clock::now() + 10s;
  bool all_dark = false;
  while (!all_dark && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(100ms);
    stats = LightStats();
    all_dark = std::all_of(stats.begin(), stats.end(),
                           [](const v1::LightStats& s) { return s.mode() == v1::LIGHT_MODE_BLACKOUT; });
  }
  const int64_t dark = MonotonicNs();
  ASSERT_TRUE(all_dark);
  ASSERT_EQ(stats.size(), 6u);
  for (const v1::LightStats& s : stats) {
    EXPECT_THAT(s.blackout_reason(), HasSubstr("controller heartbeat lost: none for 1000 ms while armed for take"));
  }
  std::printf("controller killed: every light node dark %.0f ms later (watchdog 1000 ms)\n", (dark - killed) / 1e6);
  // The world saw every emitter dark from then on, though its bus still runs.
  EXPECT_EQ(LightBetween(dark, dark + 300'000'000), 0.0);
  capture->Wait(60s);
}

}  // namespace
}  // namespace stage::testing
