// Scheduled software triggers end to end: the controller's TriggerStreamer sends each trigger ahead of its time to
// camera-node processes on loopback; each node fires its (sim) camera at that time and every trigger is accounted
// for: fired (one frame each), late or missed. Sent at their own time instead (no lead), they arrive too late.
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <filesystem>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/common/subprocess.h"
#include "stage/timing/schedule.h"
#include "stage/timing/timing_tool.h"
#include "stage/timing/trigger_scheduler.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "test_support.h"
#include "trigger_streamer.h"

namespace stage::testing {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

class ScheduledTriggersTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto loaded = LoadRig(kBuiltinRigName);
    ASSERT_TRUE(loaded.ok());
    // hs-1, hs-2 and mv-01 on scheduled software triggers; small frames so that the sim cameras keep up.
    auto rig = ApplyRigOverrides(
        *loaded, {"cameras[hs-1].trigger.source=scheduled-software", "cameras[hs-2].trigger.source=scheduled-software",
                  "cameras[mv-01].trigger.source=scheduled-software", "cameras[*].backend=sim", "cameras[*].width=64",
                  "cameras[*].height=32"});
    ASSERT_TRUE(rig.ok()) << rig.status();
    rig_ = *rig;
    auto report = timing::CheckTiming(rig_, {});
    ASSERT_TRUE(report.ok());
    schedule_ = report->schedule();
    std::string json;
    google::protobuf::util::JsonPrintOptions print;
    print.preserve_proto_field_names = true;
    ASSERT_TRUE(google::protobuf::util::MessageToJsonString(rig_.rig, &json, print).ok());
    rig_path_ = dir_.Write("rig.json", json);
    for (const char* id : {"hs-1", "hs-2", "mv-01", "mv-02"}) ASSERT_NO_FATAL_FAILURE(StartNode(id));
  }

  void StartNode(const std::string& id) {
    const std::string port_file = dir_.path() + "/" + id + ".port";
    auto p = Subprocess::Spawn({.argv = {BinDir() + "/camera-node", "--config", rig_path_, "--id", id, "--listen",
                                         "127.0.0.1:0", "--port-file", port_file, "--ptp-uds", "none"},
                                .stderr_path = dir_.path() + "/" + id + ".log"});
    ASSERT_TRUE(p.ok()) << p.status();
    nodes_.push_back(std::move(*p));
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (!std::filesystem::exists(port_file)) {
      ASSERT_FALSE(nodes_.back()->Poll().has_value()) << ReadFile(dir_.path() + "/" + id + ".log");
      ASSERT_LT(std::chrono::steady_clock::now(), deadline) << ReadFile(dir_.path() + "/" + id + ".log");
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    addresses_[id] = ReadFile(port_file);
  }

  void TearDown() override {
    for (auto& n : nodes_) n->Terminate(std::chrono::milliseconds(3000));
  }

  controller::TriggerTarget Target(const std::string& id) {
    controller::TriggerTarget t;
    t.id = id;
    t.address = addresses_.at(id);
    t.timing = *timing::FindCameraTiming(schedule_, id);
    return t;  // same host: the clock mapping stays zero
  }

  uint64_t FramesOf(const std::string& id) {
    auto stub = v1::CameraNode::NewStub(MakeChannel(addresses_.at(id)));
    grpc::ClientContext context;
    v1::CameraStats stats;
    EXPECT_TRUE(stub->GetStats(&context, v1::GetStatsRequest(), &stats).ok());
    return stats.frames_completed();
  }

  TempDir dir_;
  LoadedRig rig_;
  v1::Schedule schedule_;
  std::string rig_path_;
  std::vector<std::unique_ptr<Subprocess>> nodes_;
  std::map<std::string, std::string> addresses_;
};

TEST_F(ScheduledTriggersTest, EveryTriggerSentAheadIsFiredOrAccountedFor) {
  const int64_t slots = 400;
  controller::TriggerStreamOptions options;
  options.take_id = "take-test";
  options.t0_unix_ns = timing::TriggerScheduler::NowNs() + 300'000'000;
  options.slot_count = slots;
  options.lead_ns = schedule_.trigger_lead_slots() * 1'000'000'000LL / 912;  // the default 20 slots
  controller::TriggerStreamer streamer(options, {Target("hs-1"), Target("hs-2"), Target("mv-01")});
  streamer.Start();
  auto reports = streamer.Wait();
  const std::vector<uint64_t> expected = {400, 400, 11};  // mv-01: slots 19, 57, ..., 399
  for (size_t i = 0; i < reports.size(); ++i) {
    ASSERT_TRUE(reports[i].ok()) << reports[i].status();
    const v1::TriggerReport& r = *reports[i];
    EXPECT_EQ(r.received(), expected[i]) << i;
    EXPECT_EQ(r.fired() + r.late() + r.missed(), r.received()) << i;
    EXPECT_EQ(r.late_slots_size(), static_cast<int>(std::min<uint64_t>(100, r.late())));
    // Sent 15 to 20 slots (16 to 22 ms) ahead: half of them at least 10 ms ahead, on any machine.
    EXPECT_GT(r.median_lead_ns(), 10'000'000) << i;
    EXPECT_TRUE(r.error().empty()) << r.error();
  }
  // Each fired trigger exposed one frame on the sim camera.
  const std::vector<std::string> ids = {"hs-1", "hs-2", "mv-01"};
  for (size_t i = 0; i < ids.size(); ++i) {
    uint64_t frames = 0;
    for (int tries = 0; tries < 100 && frames < reports[i]->fired(); ++tries) {
      frames = FramesOf(ids[i]);
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    EXPECT_EQ(frames, reports[i]->fired()) << ids[i];
  }
}

// Newer clock measurements reach the node during the take and move its triggers: a node 8 ms ahead fires 8 ms
// later on its own clock, so its triggers arrive 8 ms further ahead of their (converted) time.
TEST_F(ScheduledTriggersTest, ClockUpdatesDuringTheTakeMoveTheTriggers) {
  controller::TriggerStreamOptions options;
  options.take_id = "clock-update";
  options.t0_unix_ns = timing::TriggerScheduler::NowNs() + 200'000'000;
  options.slot_count = 600;
  options.lead_ns = schedule_.trigger_lead_slots() * 1'000'000'000LL / 912;
  options.clock_update_interval_ns = 20'000'000;
  options.clock_source = [](const std::string&) -> std::optional<v1::ClockMapping> {
    v1::ClockMapping m;
    m.set_offset_ns(8'000'000);
    return m;
  };
  controller::TriggerStreamer streamer(options, {Target("hs-1")});
  streamer.Start();
  auto reports = streamer.Wait();
  ASSERT_TRUE(reports[0].ok()) << reports[0].status();
  EXPECT_EQ(reports[0]->received(), 600u);
  // Sent 16..22 ms ahead, converted 8 ms later: most arrive 24..30 ms ahead of their time on the node.
  EXPECT_GT(reports[0]->median_lead_ns(), 22'000'000);
}

TEST_F(ScheduledTriggersTest, TriggersSentAtTheirOwnTimeArriveTooLate) {
  controller::TriggerStreamOptions options;
  options.take_id = "naive";
  options.t0_unix_ns = timing::TriggerScheduler::NowNs() + 200'000'000;
  options.slot_count = 200;
  options.lead_ns = 0;
  controller::TriggerStreamer streamer(options, {Target("hs-1")});
  streamer.Start();
  auto reports = streamer.Wait();
  ASSERT_TRUE(reports[0].ok()) << reports[0].status();
  const v1::TriggerReport& r = *reports[0];
  EXPECT_EQ(r.received(), 200u);
  EXPECT_LT(r.median_lead_ns(), 0);  // half of them arrived after their time
  EXPECT_EQ(r.fired() + r.late() + r.missed(), 200u);
  EXPECT_GT(r.missed(), 0u);
  EXPECT_EQ(r.missed_slots_size(), static_cast<int>(std::min<uint64_t>(100, r.missed())));
}

TEST_F(ScheduledTriggersTest, ACameraOnTheHardwareLineRefusesTheStream) {
  controller::TriggerStreamOptions options;
  options.t0_unix_ns = timing::TriggerScheduler::NowNs() + 100'000'000;
  options.slot_count = 40;
  options.lead_ns = 20'000'000;
  controller::TriggerStreamer streamer(options, {Target("mv-02")});
  streamer.Start();
  auto reports = streamer.Wait();
  ASSERT_FALSE(reports[0].ok());
  EXPECT_EQ(reports[0].status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(reports[0].status().message(),
              AllOf(HasSubstr("camera node mv-02"), HasSubstr("not triggered by scheduled software triggers")));
}

// A camera node that takes the stream and then never answers: its handler waits until the call is cancelled.
class StuckCameraNode final : public v1::CameraNode::Service {
 public:
  grpc::Status StreamTriggers(grpc::ServerContext* context, grpc::ServerReader<v1::TriggerStreamMessage>*,
                              v1::TriggerReport*) override {
    while (!context->IsCancelled()) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
  }
};

TEST(TriggerStreamerTest, AStuckNodeCannotHoldTheStreamer) {
  StuckCameraNode stuck;
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&stuck});
  ASSERT_TRUE(server.ok());
  auto base = timing::TimeBase::Create(912);
  controller::TriggerTarget target;
  target.id = "hs-9";
  target.address = (*server)->address();
  target.timing.set_divider(1);
  target.timing.set_late_slack_ticks(base->UsToTicks(100));

  // Cancel() ends the stream although the node never answers.
  controller::TriggerStreamOptions options;
  options.t0_unix_ns = timing::TriggerScheduler::NowNs() + 50'000'000;
  options.slot_count = 100'000;  // about two minutes of slots
  options.lead_ns = 20'000'000;
  controller::TriggerStreamer streamer(options, {target});
  streamer.Start();
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  streamer.Cancel();
  auto results = streamer.Wait();
  ASSERT_FALSE(results[0].ok());
  EXPECT_EQ(results[0].status().code(), absl::StatusCode::kCancelled) << results[0].status();

  // Without Cancel(), the deadline (last slot + finish_timeout_ms) ends it.
  options.t0_unix_ns = timing::TriggerScheduler::NowNs() + 20'000'000;
  options.slot_count = 50;
  options.finish_timeout_ms = 300;
  controller::TriggerStreamer timed(options, {target});
  timed.Start();
  results = timed.Wait();
  ASSERT_FALSE(results[0].ok());
  EXPECT_EQ(results[0].status().code(), absl::StatusCode::kDeadlineExceeded) << results[0].status();
}

}  // namespace
}  // namespace stage::testing
