// The simulated stage with its four Modbus light nodes on fake LED boards (sim.modbus_fakes): stage-sim hosts a
// libmodbus server per node on loopback, whose LEDs light the world on its slot clock, and the light nodes run the
// real Modbus backend against them (upload, read-back, arm, status poll). A clean take is complete and aligned (four of
// the six light nodes' light comes from the boards: a board that did not step would break every cycle's signature);
// a board that stops answering mid-take is reported, by node and cause, and the take is DEGRADED; once it answers
// again, the next take is complete.
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;
using namespace std::chrono_literals;

class ModbusStageTest : public SimulatedStageTest {
 protected:
  void StartModbusStage(const std::string& take_root, std::vector<std::string> extra = {}) {
    std::vector<std::string> args = ControlPlaneScene({"--take-root", take_root, "--set", "sim.modbus_fakes=true"});
    for (std::string& e : extra) {
      args.push_back("--set");
      args.push_back(std::move(e));
    }
    StartStage(args);
  }

  // Light node id -> the backend its process reports.
  std::map<std::string, std::string> LightBackends() {
    std::map<std::string, std::string> backends;
    for (const auto& p : endpoints_.processes()) {
      if (p.kind() != v1::NODE_KIND_LIGHT) continue;
      auto stub = v1::LightNode::NewStub(MakeChannel(p.address()));
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + 10s);
      v1::NodeInfo info;
      EXPECT_TRUE(stub->GetInfo(&context, v1::GetInfoRequest(), &info).ok()) << p.id();
      backends[p.id()] = info.backend();
    }
    return backends;
  }

  static void ExpectAligned(const nlohmann::json& take) {
    ASSERT_EQ(take["alignment"].size(), 3u) << take.dump();
    for (const auto& a : take["alignment"]) EXPECT_TRUE(a["ok"].get<bool>()) << a.dump();
  }
};

TEST_F(ModbusStageTest, ATakeLitByFakeLedBoardsIsCompleteAndAligned) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartModbusStage(root.path()));
  EXPECT_EQ(LightBackends(), (std::map<std::string, std::string>{{"lights-modbus-1", "modbus"},
                                                                 {"lights-modbus-2", "modbus"},
                                                                 {"lights-modbus-3", "modbus"},
                                                                 {"lights-modbus-4", "modbus"},
                                                                 {"lights-gpio-1", "sim"},
                                                                 {"lights-gpio-2", "sim"}}));
  CommandResult capture = Stagectl({"capture", "--frames", "8", "--json", "--no-ground-truth"});
  ASSERT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE");
  EXPECT_EQ(take["hint"], "");
  ExpectAligned(take);
}

TEST_F(ModbusStageTest, ABoardThatStopsAnsweringIsReportedAndTheTakeIsDegraded) {
  TempDir root;
  // lights-modbus-2's board goes silent 0.05 s into the world (the first take) for 1 s of wall time. The lockstep
  // world runs at the speed it renders 27 cameras: the 1 s take lasts about 25 s of wall time on the 2-core
  // development machine, so the light node's 250 ms status poll finds the board silent while armed. (A machine that
  // rendered the take in under a second would see the disarm fail instead.)
  ASSERT_NO_FATAL_FAILURE(
      StartModbusStage(root.path(), {"sim.faults[0].target=lights-modbus-2", "sim.faults[0].board_silent_at_s=0.05",
                                     "sim.faults[0].board_silent_s=1"}));
  CommandResult capture = Stagectl({"capture", "--frames", "24", "--json", "--no-ground-truth"});
  EXPECT_EQ(capture.exit.exit_code, 4) << capture.out << capture.err;  // DEGRADED
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_DEGRADED");
  const std::string hint = take["hint"];
  EXPECT_THAT(hint, HasSubstr("lights-modbus-2"));
  EXPECT_THAT(hint, HasSubstr("board not answering: status poll (register 0x0110)"));
  for (const std::string other : {"lights-modbus-1", "lights-modbus-3", "lights-modbus-4"}) {
    EXPECT_THAT(hint, ::testing::Not(HasSubstr(other))) << "only the silent board is named";
  }
  // Its LEDs kept stepping (the bus broke, not the board): every frame is stored and the cycles are aligned.
  EXPECT_EQ(take["total"]["expected"], take["total"]["stored"]);
  ExpectAligned(take);
  // The board answers again: the next take is clean.
  std::this_thread::sleep_for(1s);
  CommandResult next = Stagectl({"capture", "--frames", "4", "--json", "--no-ground-truth"});
  EXPECT_EQ(next.exit.exit_code, 0) << next.out << next.err;
  EXPECT_EQ(nlohmann::json::parse(next.out)["hint"], "");
}

}  // namespace
}  // namespace stage::testing
