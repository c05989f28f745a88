// The contract as a third-party client meets it: the Python example client (examples/python, stubs generated from
// proto/ by protoc's gRPC Python plugin, Debian's python3-grpcio and python3-protobuf) against a simulated stage. Its
// status matches stagectl's; a capture names its take in its first event and ends COMPLETE with the summary stagectl
// shows; a second client follows the running take to the same end; the ledger comes page by page, every entry of it.
#include <grpcpp/grpcpp.h>

#include <nlohmann/json.hpp>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/controller.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

class PythonClientTest : public SimulatedStageTest {
 protected:
  void SetUp() override {
    CommandResult generated = RunCommand({source_ + "/examples/python/generate.sh", stubs_.path()}, kSlow);
    ASSERT_EQ(generated.exit.exit_code, 0) << generated.err;
  }
  // The client, as a user runs it (Debian's python3, with its grpcio and protobuf).
  CommandResult Client(std::vector<std::string> args) {
    args.insert(args.begin(), {"/usr/bin/python3", source_ + "/examples/python/fastage_client.py", "--stubs",
                               stubs_.path(), "--endpoints", Endpoints()});
    return RunCommand(args, kSlow);
  }
  static constexpr std::chrono::seconds kSlow{300};
  const std::string source_ = FASTAGE_SOURCE_DIR;
  TempDir stubs_;
};

TEST_F(PythonClientTest, StatusCaptureWatchAndLedgerFromPython) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));

  // Status: the same message stagectl prints.
  CommandResult status = Client({"status", "--json"});
  ASSERT_EQ(status.exit.exit_code, 0) << status.err;
  const nlohmann::json from_python = nlohmann::json::parse(status.out);
  const nlohmann::json from_stagectl = StatusJson();
  EXPECT_EQ(from_python["stage_id"], from_stagectl["stage_id"]);
  EXPECT_EQ(from_python["nodes_total"], 34);
  EXPECT_EQ(from_python["session_state"], "SESSION_STATE_IDLE");
  EXPECT_EQ(from_python["nodes"][0]["camera_role"], "CAMERA_ROLE_MACHINE_VISION");

  // A capture from Python while a second Python client follows it: both see it to its end.
  auto capture = Subprocess::Spawn(
      {.argv = {"/usr/bin/python3", source_ + "/examples/python/fastage_client.py", "--stubs", stubs_.path(),
                "--endpoints", Endpoints(), "capture", "--frames", "3", "--name", "python", "--json"},
       .stdout_path = run_dir_.path() + "/py-capture.out",
       .stderr_path = run_dir_.path() + "/py-capture.err"});
  ASSERT_TRUE(capture.ok()) << capture.status();
  ASSERT_TRUE(WaitForSession("capturing", kSlow)) << ReadFile(run_dir_.path() + "/py-capture.err");
  CommandResult watched = Client({"watch", "--json"});
  auto captured = (*capture)->Wait(kSlow);
  ASSERT_TRUE(captured.has_value());
  EXPECT_EQ(captured->exit_code, 0) << ReadFile(run_dir_.path() + "/py-capture.err");
  const nlohmann::json take = nlohmann::json::parse(ReadFile(run_dir_.path() + "/py-capture.out"));
  const std::string id = take["take_id"];
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE");
  // The take's id came with the first event, before its first state.
  const std::string events = ReadFile(run_dir_.path() + "/py-capture.err");
  EXPECT_EQ(events.rfind("take " + id + "\nsession: configuring\n", 0), 0u) << events;
  EXPECT_EQ(watched.exit.exit_code, 0) << watched.err;
  EXPECT_EQ(nlohmann::json::parse(watched.out)["take_id"], id);
  EXPECT_EQ(nlohmann::json::parse(watched.out)["total"], take["total"]);
  // The same summary as stagectl shows.
  CommandResult shown = Stagectl({"take", "show", id, "--json"});
  ASSERT_EQ(shown.exit.exit_code, 0) << shown.err;
  EXPECT_EQ(nlohmann::json::parse(shown.out)["total"], take["total"]);

  // The ledger, 50 entries a page: every expected (camera, slot) once, none lost.
  CommandResult ledger = Client({"ledger", id, "--page-size", "50", "--json"});
  ASSERT_EQ(ledger.exit.exit_code, 0) << ledger.err;
  const nlohmann::json pages = nlohmann::json::parse(ledger.out);
  const int64_t expected = std::stoll(take["total"]["expected"].get<std::string>());
  EXPECT_EQ(pages["total"], expected);
  EXPECT_EQ(static_cast<int64_t>(pages["entries"].size()), expected);
  EXPECT_EQ(pages["pages"], (expected + 49) / 50);
  EXPECT_EQ(pages["entries"][0]["reason"], "LOSS_REASON_STORED");
  CommandResult lost = Client({"ledger", id, "--lost", "--json"});
  ASSERT_EQ(lost.exit.exit_code, 0) << lost.err;
  EXPECT_EQ(nlohmann::json::parse(lost.out)["total"], 0);

  // A take that has ended: following it gives its verdict at once.
  CommandResult again = Client({"watch", id});
  EXPECT_EQ(again.exit.exit_code, 0) << again.err;
  EXPECT_THAT(again.out, HasSubstr("take " + id + ": COMPLETE"));
  // Nothing running: NOT_FOUND, said so.
  CommandResult none = Client({"watch"});
  EXPECT_EQ(none.exit.exit_code, 2);
  EXPECT_THAT(none.err, HasSubstr("NOT_FOUND: no take is running"));
}

// Frames and seconds both: refused, naming both, whoever asks (stagectl refuses it before asking).
TEST_F(PythonClientTest, ACaptureWithFramesAndSecondsIsRefused) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  auto stub = v1::StageController::NewStub(MakeChannel(endpoints_.controller()));
  grpc::ClientContext context;
  v1::CaptureRequest request;
  request.set_frames(2);
  request.set_seconds(1);
  auto reader = stub->Capture(&context, request);
  v1::CaptureEvent event;
  EXPECT_FALSE(reader->Read(&event));
  const grpc::Status s = reader->Finish();
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(s.error_message(), HasSubstr("give frames or seconds, not both (frames 2, seconds 1)"));
  EXPECT_EQ(SessionState(), "idle");
}

}  // namespace
}  // namespace stage::testing
