// The simulated stage with four of its machine-vision cameras on GigE Vision (sim.gige_fakes): stage-sim hosts a
// fake GigE Vision camera per camera (Aravis's ArvGvFakeCamera, rendering the stage) at its own loopback address, and
// the camera nodes run the real Aravis backend against them, over GVCP and GVSP. Takes are captured with stagectl and
// checked in the ledger (sqlite3 shell), the frame files (h5dump) and the nodes' statistics: a clean take is complete;
// with packets lost on one camera's link, every incomplete frame is in the ledger as lost with its reason and the
// counts reconcile exactly; a camera that leaves the network mid-take is reconnected with its settings restored,
// and the outage is in its status and its ledger. The suite runs in a network namespace of its own.
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <iostream>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "net_namespace.h"
#include "simulated_stage.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

std::string g_why_not = "not set up";

const std::vector<std::string> kGigE = {"mv-01", "mv-02", "mv-03", "mv-04"};

class GigEStageTest : public SimulatedStageTest {
 protected:
  void SetUp() override {
    if (!g_why_not.empty()) GTEST_SKIP() << "needs a network namespace of its own: " << g_why_not;
  }

  // The stage with kGigE on fake GigE Vision cameras at 127.0.0.11.. (the other cameras simulated as usual), and
  // `extra` rig overrides.
  void StartGigEStage(const std::string& take_root, std::vector<std::string> extra = {}) {
    std::vector<std::string> args = ControlPlaneScene(
        {"--take-root", take_root, "--set", "sim.gige_fakes=true", "--set", "cameras[mv-*].backend=sim"});
    for (size_t i = 0; i < kGigE.size(); ++i) {
      const std::string c = "cameras[" + kGigE[i] + "].";
      // A 256x192 region of the sensor: Aravis enlarges a stream's receive buffer only once the first frame's leader
      // is in, so the first frame must fit the kernel's default (net.core.rmem_default, about 200 KiB here, which a
      // network namespace cannot raise), and a loaded two-core machine must drain each frame before the next.
      for (std::string set : {c + "backend=aravis", c + "device=127.0.0." + std::to_string(11 + i),
                              c + "gige.packet_socket=false", c + "width=256", c + "height=192"}) {
        args.push_back("--set");
        args.push_back(set);
      }
    }
    for (std::string& e : extra) {
      args.push_back("--set");
      args.push_back(std::move(e));
    }
    StartStage(args);
  }

  std::string Sql(const std::string& root, const std::string& query) {
    CommandResult r = RunCommand({"/usr/bin/sqlite3", root + "/catalog.sqlite", query}, std::chrono::seconds(30));
    EXPECT_EQ(r.exit.exit_code, 0) << r.err;
    return r.out;
  }
  int64_t Count(const std::string& root, const std::string& take, const std::string& camera, const std::string& where) {
    return std::stoll(Sql(
        root, "SELECT count(*) FROM ledger WHERE take_id='" + take + "' AND camera_id='" + camera + "' AND " + where));
  }

  // What the take lost, for a failure's message.
  std::string Lost(const std::string& root, const std::string& take) {
    return Sql(root, "SELECT camera_id, slot, reason, detail FROM ledger WHERE take_id='" + take +
                         "' AND reason != 0 LIMIT 40");
  }

  v1::CameraStats Stats(const std::string& id) {
    for (const auto& p : endpoints_.processes()) {
      if (p.id() != id) continue;
      auto stub = v1::CameraNode::NewStub(MakeChannel(p.address()));
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
      v1::CameraStats stats;
      EXPECT_TRUE(stub->GetStats(&context, v1::GetStatsRequest(), &stats).ok()) << id;
      return stats;
    }
    ADD_FAILURE() << "no process " << id;
    return {};
  }

  // Frames of each status (1 whole, 2 incomplete) in a camera's frame file, by h5dump.
  std::map<int64_t, int64_t> FileStatuses(const std::string& path) {
    std::map<int64_t, int64_t> n;
    for (int64_t s : ReadH5Column(path, "/status")) ++n[s];
    return n;
  }
};

// A clean take: every GigE camera's frames, through the camera nodes' Aravis backend and the normal capture path,
// are in the ledger as stored and in the files; the nodes' statistics count them and no failure.
TEST_F(GigEStageTest, ATakeOnFourFakeGigECamerasIsCompleteInTheLedger) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartGigEStage(root.path()));
  CommandResult capture = Stagectl({"capture", "--frames", "8", "--json"});
  const std::string take = nlohmann::json::parse(capture.out)["take_id"];
  ASSERT_EQ(capture.exit.exit_code, 0) << capture.err << Lost(root.path(), take);
  for (const std::string& id : kGigE) {
    SCOPED_TRACE(id);
    EXPECT_EQ(Count(root.path(), take, id, "reason=0"), 8);
    EXPECT_EQ(Count(root.path(), take, id, "reason!=0"), 0);
    const std::string file = root.path() + "/" + take + "/cameras/" + id + ".h5";
    EXPECT_EQ(FileStatuses(file), (std::map<int64_t, int64_t>{{1, 8}}));  // all whole
    std::vector<int64_t> slots = ReadH5Column(file, "/slot");
    ASSERT_EQ(slots.size(), 8u);
    for (size_t i = 1; i < slots.size(); ++i) EXPECT_EQ(slots[i] - slots[i - 1], 38) << i;
    const v1::CameraStats stats = Stats(id);
    EXPECT_EQ(stats.frames_completed(), 8u);
    EXPECT_EQ(stats.frames_failed(), 0u);
    EXPECT_TRUE(stats.link_up());
  }
}

// Packets lost on mv-02's link (5 % of them: a third of its frames hit, packet resend off): each frame with data
// missing is in its file marked incomplete and in the ledger lost as "incomplete"; a frame whose leader was lost
// cannot be delivered and is in the ledger as exposed and not delivered (the frame counter's gap). Ledger, file and
// the node's stream statistics agree exactly, and the other cameras lost nothing.
TEST_F(GigEStageTest, PacketLossIsCountedAndAttributedFrameByFrame) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartGigEStage(root.path(), {"sim.faults[0].target=mv-02", "sim.faults[0].packet_loss=0.05",
                                                       "cameras[mv-02].gige.packet_resend=false"}));
  CommandResult capture = Stagectl({"capture", "--frames", "24", "--json"});
  const std::string take = nlohmann::json::parse(capture.out)["take_id"];
  const int64_t stored = Count(root.path(), take, "mv-02", "reason=0");
  const int64_t incomplete = Count(root.path(), take, "mv-02", "reason=6");
  const int64_t dropped = Count(root.path(), take, "mv-02", "reason=1");
  EXPECT_EQ(stored + incomplete + dropped, 24)
      << Sql(root.path(), "SELECT slot, reason, detail FROM ledger WHERE take_id='" + take + "' AND camera_id='mv-02'");
  EXPECT_GT(incomplete, 0);
  EXPECT_EQ(capture.exit.exit_code, incomplete + dropped > 0 ? 4 : 0) << capture.err;  // DEGRADED
  const std::string file = root.path() + "/" + take + "/cameras/mv-02.h5";
  std::map<int64_t, int64_t> in_file = FileStatuses(file);
  EXPECT_EQ(in_file[1], stored);
  EXPECT_EQ(in_file[2], incomplete);
  // Every incomplete entry says what was missing.
  EXPECT_EQ(Count(root.path(), take, "mv-02", "reason=6 AND detail LIKE '%missing%'") +
                Count(root.path(), take, "mv-02", "reason=6 AND detail LIKE '%timeout%'"),
            incomplete);
  const v1::CameraStats stats = Stats("mv-02");
  EXPECT_EQ(stats.frames_completed(), static_cast<uint64_t>(stored + incomplete));  // delivered, whole or not
  EXPECT_EQ(stats.frames_failed(), static_cast<uint64_t>(incomplete + dropped));    // the stream's failures
  EXPECT_GT(stats.packets_missing(), 0u);
  std::cout << "mv-02 with 5 % of its packets lost: " << stored << " stored, " << incomplete << " incomplete, "
            << dropped << " exposed and not delivered (leader lost) of 24; the node: " << stats.frames_completed()
            << " delivered, " << stats.frames_failed() << " failed, " << stats.packets_missing()
            << " packets missing\n";
  for (const char* id : {"mv-01", "mv-03", "mv-04"}) {
    EXPECT_EQ(Count(root.path(), take, id, "reason=0"), 24) << id;
  }
}

// mv-03's fake camera leaves the network early in a take and comes back power-cycled a second later: the camera
// node stays up, regains control, restores its settings and streams again; its status tells the outage, and its ledger
// gives the slots in between as "link down" with the outage's times. The next take is complete.
TEST_F(GigEStageTest, ACameraThatLeavesTheNetworkIsReconnectedAndItsOutageIsInTheLedger) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartGigEStage(
      root.path(), {"sim.faults[0].target=mv-03", "sim.faults[0].link_down_at_s=0.3", "sim.faults[0].link_down_s=1"}));
  CommandResult capture = Stagectl({"capture", "--frames", "48", "--json"});
  EXPECT_EQ(capture.exit.exit_code, 4) << capture.err;  // DEGRADED
  const std::string take = nlohmann::json::parse(capture.out)["take_id"];
  const int64_t down = Count(root.path(), take, "mv-03", "reason=8");
  EXPECT_GT(down, 0) << Sql(
      root.path(), "SELECT slot, reason, detail FROM ledger WHERE take_id='" + take + "' AND camera_id='mv-03'");
  EXPECT_EQ(Count(root.path(), take, "mv-03", "reason=8 AND detail LIKE 'link down %'") +
                Count(root.path(), take, "mv-03", "reason=8 AND detail LIKE 'control of the camera lost%'"),
            down);
  EXPECT_EQ(Count(root.path(), take, "mv-03", "reason=0") + down, 48)
      << Sql(root.path(), "SELECT slot, reason, detail FROM ledger WHERE take_id='" + take + "' AND camera_id='mv-03'");
  EXPECT_EQ(Count(root.path(), take, "mv-01", "reason=0"), 48);

  // The node reconnects (if the take ended first, it does so now) and says so.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  v1::CameraStats stats = Stats("mv-03");
  while (stats.reconnects() == 0 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    stats = Stats("mv-03");
  }
  EXPECT_EQ(stats.link_losses(), 1u);
  ASSERT_EQ(stats.reconnects(), 1u) << stats.link_detail();
  EXPECT_TRUE(stats.link_up());
  EXPECT_THAT(stats.link_detail(), HasSubstr("settings restored"));
  CommandResult status = Stagectl({"status", "--cameras", "--json"});
  ASSERT_EQ(status.exit.exit_code, 0) << status.err;
  nlohmann::json cameras = nlohmann::json::parse(status.out)["cameras"];
  bool found = false;
  for (const auto& c : cameras) {
    if (c["id"] != "mv-03") continue;
    found = true;
    EXPECT_EQ(c["stats"]["link_losses"], "1");
    EXPECT_EQ(c["stats"]["reconnects"], "1");
  }
  EXPECT_TRUE(found) << status.out;

  // Streaming again with the settings restored: the next take is whole, at the rig's size.
  CommandResult again = Stagectl({"capture", "--frames", "8", "--json"});
  ASSERT_EQ(again.exit.exit_code, 0) << again.err;
  const std::string second = nlohmann::json::parse(again.out)["take_id"];
  EXPECT_EQ(Count(root.path(), second, "mv-03", "reason=0"), 8);
  CommandResult header =
      RunCommand({"/usr/bin/h5dump", "-H", root.path() + "/" + second + "/cameras/mv-03.h5"}, std::chrono::seconds(30));
  EXPECT_THAT(header.out, HasSubstr("192, 256"));  // the rig's region, not the fake's power-on size
}

}  // namespace
}  // namespace stage::testing

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  // The fake cameras listen at 127.0.0.11-14, in a network namespace of this process's own (stage-sim and its nodes,
  // its children, are in it too).
  stage::testing::g_why_not = stage::testing::IsolateNetwork(11, 14);
  return RUN_ALL_TESTS();
}
