// The simulated stage on mutual TLS (the rig's security, certificates from scripts/make-test-certs), on loopback: a
// take is COMPLETE; an observer reads but cannot capture; a camera's certificate cannot drive a light node; a
// certificate of another CA and a plain-text client are refused, each said in the refusing side's log.
#include <grpcpp/grpcpp.h>

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

class TlsStageTest : public SimulatedStageTest {
 protected:
  // Certificates of every identity of the shipped rig, stage-sim's, an operator's and an observer's, in `dir`; and
  // another CA's operator in `dir`/other.
  void MakeCerts(const std::string& dir) {
    auto rig = LoadRig("builtin:fastage");
    ASSERT_TRUE(rig.ok()) << rig.status();
    std::vector<std::string> argv = {std::string(FASTAGE_SOURCE_DIR) + "/scripts/make-test-certs",
                                     dir,
                                     "controller",
                                     "sim",
                                     "operator/tester",
                                     "observer/watcher"};
    for (const auto& c : rig->rig.cameras()) argv.push_back("camera/" + c.id());
    for (const auto& n : rig->rig.light_nodes()) argv.push_back("light/" + n.id());
    for (const auto& w : rig->rig.processing_workers()) argv.push_back("worker/" + w.id());
    CommandResult made = RunCommand(argv, std::chrono::seconds(120));
    ASSERT_EQ(made.exit.exit_code, 0) << made.err;
    CommandResult other = RunCommand({argv[0], dir + "/other", "operator/tester"}, std::chrono::seconds(60));
    ASSERT_EQ(other.exit.exit_code, 0) << other.err;
  }

  static std::vector<std::string> MutualTls(const std::string& dir, std::vector<std::string> more) {
    std::vector<std::string> args = {"--set", "security.transport=mutual-tls",
                                     "--set", "security.ca_file=" + dir + "/ca.crt",
                                     "--set", "security.cert_dir=" + dir};
    for (auto& m : more) args.push_back(std::move(m));
    return args;
  }

  static TransportSecurity As(const std::string& dir, const std::string& file) {
    return {.mode = TransportSecurity::Mode::kMutualTls,
            .ca_file = dir + "/ca.crt",
            .cert_file = dir + "/" + file + ".crt",
            .key_file = dir + "/" + file + ".key"};
  }

  const v1::SimProcess& Process(v1::NodeKind kind) {
    for (const auto& p : endpoints_.processes()) {
      if (p.kind() == kind) return p;
    }
    ADD_FAILURE() << "no process of kind " << kind;
    return endpoints_.processes(0);
  }
};

TEST_F(TlsStageTest, ATakeOverMutualTlsIsCompleteAndCallersWithoutTheRightCertificateAreRefused) {
  TempDir certs, root;
  ASSERT_NO_FATAL_FAILURE(MakeCerts(certs.path()));
  ASSERT_NO_FATAL_FAILURE(StartStage(MutualTls(certs.path(), ControlPlaneScene({"--take-root", root.path()}))));
  EXPECT_THAT(ReadFile(Process(v1::NODE_KIND_CONTROLLER).log_file()), HasSubstr("transport: mutual TLS as controller"));

  CommandResult capture = Stagectl({"--as", "operator/tester", "capture", "--frames", "2", "--json"});
  ASSERT_EQ(capture.exit.exit_code, 0) << capture.err;
  EXPECT_EQ(nlohmann::json::parse(capture.out)["outcome"], "TAKE_OUTCOME_COMPLETE");

  // An observer reads the stage and may not capture.
  CommandResult status = Stagectl({"--as", "observer/watcher", "status", "--json"});
  EXPECT_EQ(status.exit.exit_code, 0) << status.err;
  CommandResult refused = Stagectl({"--as", "observer/watcher", "capture", "--frames", "2"});
  EXPECT_NE(refused.exit.exit_code, 0);
  EXPECT_THAT(refused.err, HasSubstr("observer/watcher may not call /stage.v1.StageController/Capture"));
  EXPECT_THAT(ReadFile(Process(v1::NODE_KIND_CONTROLLER).log_file()),
              HasSubstr("rpc.auth: refused observer/watcher calling /stage.v1.StageController/Capture"));

  // A camera's certificate cannot drive lights: refused, and said in the light node's log.
  const v1::SimProcess& light = Process(v1::NODE_KIND_LIGHT);
  std::string camera_file;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() == v1::NODE_KIND_CAMERA && camera_file.empty()) camera_file = "camera-" + p.id();
  }
  auto as_camera =
      v1::LightNode::NewStub(MakeChannel(light.address(), grpc::ChannelArguments(), As(certs.path(), camera_file)));
  grpc::ClientContext arm_context;
  v1::LightStats armed;
  const grpc::Status arm = as_camera->Arm(&arm_context, v1::ArmLightRequest(), &armed);
  EXPECT_EQ(arm.error_code(), grpc::StatusCode::PERMISSION_DENIED) << arm.error_message();
  EXPECT_THAT(ReadFile(light.log_file()), HasSubstr("rpc.auth: refused camera/"));
  EXPECT_THAT(ReadFile(light.log_file()), HasSubstr("calling /stage.v1.LightNode/Arm"));

  // Another CA's certificate, and plain text: the controller refuses both connections and says why.
  auto call_controller = [&](const TransportSecurity& as) {
    auto stub = v1::StageController::NewStub(MakeChannel(endpoints_.controller(), grpc::ChannelArguments(), as));
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
    v1::StageStatus response;
    return stub->GetStageStatus(&context, v1::GetStageStatusRequest(), &response);
  };
  // (It trusts the stage's CA: the refusal is the controller's, of its certificate.)
  TransportSecurity foreign = As(certs.path() + "/other", "operator-tester");
  foreign.ca_file = certs.path() + "/ca.crt";
  EXPECT_EQ(call_controller(foreign).error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ(call_controller(TransportSecurity()).error_code(), grpc::StatusCode::UNAVAILABLE);
  const std::string controller_log = ReadFile(Process(v1::NODE_KIND_CONTROLLER).log_file());
  EXPECT_THAT(controller_log, HasSubstr("rpc.tls: refused a connection: TLS handshake failed: the peer's certificate "
                                        "is not signed by this stage's CA"));
  EXPECT_THAT(controller_log, HasSubstr("rpc.tls: refused a connection: TLS handshake failed: the peer does not "
                                        "speak TLS"));
  EXPECT_EQ(call_controller(As(certs.path(), "operator-tester")).error_code(), grpc::StatusCode::OK);
}

}  // namespace
}  // namespace stage::testing
