// The simulated stage on mutual TLS (the rig's security, certificates from scripts/make-test-certs), on loopback and
// across hosts (network namespaces the test makes, joined by veth links to a bridge): a take is COMPLETE; an observer
// reads but cannot capture; a camera's certificate cannot drive a light node; a certificate of another CA and a
// plain-text client are refused, each said in the refusing side's log; across hosts, a replaced certificate is used
// without a restart. The suite runs in a network namespace of its own.
#include <grpcpp/grpcpp.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "net_namespace.h"
#include "simulated_stage.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

std::string g_why_not = "not set up";

class TlsStageTest : public SimulatedStageTest {
 protected:
  void SetUp() override {
    if (!g_why_not.empty()) GTEST_SKIP() << "needs a network namespace of its own: " << g_why_not;
  }

  static std::string MakeTestCerts() { return std::string(FASTAGE_SOURCE_DIR) + "/scripts/make-test-certs"; }

  // Certificates of every identity of the shipped rig, stage-sim's, an operator's and an observer's, in `dir`, each
  // good for loopback and `ips` (the addresses processes are dialled at); and another CA's operator in `dir`/other.
  void MakeCerts(const std::string& dir, const std::vector<std::string>& ips = {}) {
    auto rig = LoadRig("builtin:fastage");
    ASSERT_TRUE(rig.ok()) << rig.status();
    std::vector<std::string> argv = {MakeTestCerts()};
    for (const std::string& ip : ips) {
      argv.push_back("--ip");
      argv.push_back(ip);
    }
    argv.push_back(dir);
    for (const char* id : {"controller", "sim", "operator/tester", "observer/watcher"}) argv.push_back(id);
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

  // GetStageStatus on a connection of its own (no subchannel shared with earlier calls), as `as`; the certificate the
  // controller presented, in PEM, into `*server_pem` when not null.
  grpc::Status CallController(const TransportSecurity& as, std::string* server_pem = nullptr) {
    grpc::ChannelArguments args;
    args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
    auto stub = v1::StageController::NewStub(MakeChannel(endpoints_.controller(), args, as));
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
    v1::StageStatus response;
    grpc::Status status = stub->GetStageStatus(&context, v1::GetStageStatusRequest(), &response);
    if (server_pem != nullptr && context.auth_context() != nullptr) {
      for (const auto& v : context.auth_context()->FindPropertyValues("x509_pem_cert")) server_pem->assign(v.data(), v.size());
    }
    return status;
  }

  // A take as an operator is COMPLETE; an observer reads and may not capture; a camera's certificate may not arm a
  // light node; another CA's certificate and plain text are refused. Each refusal is in the refusing side's log.
  void CheckTakeAndRefusals(const std::string& certs) {
    CommandResult capture = Stagectl({"--as", "operator/tester", "capture", "--frames", "2", "--json"});
    ASSERT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
    EXPECT_EQ(nlohmann::json::parse(capture.out)["outcome"], "TAKE_OUTCOME_COMPLETE");

    CommandResult status = Stagectl({"--as", "observer/watcher", "status", "--json"});
    EXPECT_EQ(status.exit.exit_code, 0) << status.err;
    CommandResult refused = Stagectl({"--as", "observer/watcher", "capture", "--frames", "2"});
    EXPECT_NE(refused.exit.exit_code, 0);
    EXPECT_THAT(refused.err, HasSubstr("observer/watcher may not call /stage.v1.StageController/Capture"));
    EXPECT_THAT(ReadFile(Process(v1::NODE_KIND_CONTROLLER).log_file()),
                HasSubstr("rpc.auth: refused observer/watcher calling /stage.v1.StageController/Capture"));

    const v1::SimProcess& light = Process(v1::NODE_KIND_LIGHT);
    std::string camera_file;
    for (const auto& p : endpoints_.processes()) {
      if (p.kind() == v1::NODE_KIND_CAMERA && camera_file.empty()) camera_file = "camera-" + p.id();
    }
    auto as_camera =
        v1::LightNode::NewStub(MakeChannel(light.address(), grpc::ChannelArguments(), As(certs, camera_file)));
    grpc::ClientContext arm_context;
    v1::LightStats armed;
    const grpc::Status arm = as_camera->Arm(&arm_context, v1::ArmLightRequest(), &armed);
    EXPECT_EQ(arm.error_code(), grpc::StatusCode::PERMISSION_DENIED) << arm.error_message();
    EXPECT_THAT(ReadFile(light.log_file()), HasSubstr("rpc.auth: refused camera/"));
    EXPECT_THAT(ReadFile(light.log_file()), HasSubstr("calling /stage.v1.LightNode/Arm"));

    // (It trusts the stage's CA: the refusal is the controller's, of its certificate.)
    TransportSecurity foreign = As(certs + "/other", "operator-tester");
    foreign.ca_file = certs + "/ca.crt";
    EXPECT_EQ(CallController(foreign).error_code(), grpc::StatusCode::UNAVAILABLE);
    EXPECT_EQ(CallController(TransportSecurity()).error_code(), grpc::StatusCode::UNAVAILABLE);
    const std::string controller_log = ReadFile(Process(v1::NODE_KIND_CONTROLLER).log_file());
    EXPECT_THAT(controller_log, HasSubstr("rpc.tls: refused a connection: TLS handshake failed: the peer's "
                                          "certificate is not signed by this stage's CA"));
    EXPECT_THAT(controller_log, HasSubstr("rpc.tls: refused a connection: TLS handshake failed: the peer does not "
                                          "speak TLS"));
    EXPECT_EQ(CallController(As(certs, "operator-tester")).error_code(), grpc::StatusCode::OK);
  }
};

TEST_F(TlsStageTest, ATakeOverMutualTlsIsCompleteAndCallersWithoutTheRightCertificateAreRefused) {
  TempDir certs, root;
  ASSERT_NO_FATAL_FAILURE(MakeCerts(certs.path()));
  ASSERT_NO_FATAL_FAILURE(StartStage(MutualTls(certs.path(), ControlPlaneScene({"--take-root", root.path()}))));
  EXPECT_THAT(ReadFile(Process(v1::NODE_KIND_CONTROLLER).log_file()), HasSubstr("transport: mutual TLS as controller"));
  ASSERT_NO_FATAL_FAILURE(CheckTakeAndRefusals(certs.path()));
}

TEST_F(TlsStageTest, AcrossHostsTheStageRunsOnMutualTlsAndAReplacedCertificateIsUsedWithoutARestart) {
  // Three hosts on a bridge: the cameras on one, the light nodes on another, the controller and the processing worker
  // on a third; stage-sim's world on the bridge's own address.
  TestHosts hosts(3);
  // As the suite's own namespace: without the privilege to make them (root), it says so and skips.
  if (!hosts.why_not().empty()) GTEST_SKIP() << hosts.why_not();
  TempDir certs, root;
  ASSERT_NO_FATAL_FAILURE(MakeCerts(certs.path(), {TestHosts::Hub(), TestHosts::Address(1), TestHosts::Address(2),
                                                   TestHosts::Address(3)}));
  auto place = [&](const std::string& who, int host) {
    return who + "=" + hosts.Name(host) + "/" + TestHosts::Address(host);
  };
  ASSERT_NO_FATAL_FAILURE(StartStage(MutualTls(
      certs.path(),
      ControlPlaneScene({"--take-root", root.path(), "--set", "security.reload_interval_s=1", "--world-listen",
                         TestHosts::Hub() + ":0", "--place", place("camera", 1), "--place", place("light", 2),
                         "--place", place("worker", 3), "--place", place("controller", 3)}))));
  // Every node is where it was placed, on its host's address.
  for (const auto& p : endpoints_.processes()) {
    const int host = p.kind() == v1::NODE_KIND_CAMERA ? 1 : p.kind() == v1::NODE_KIND_LIGHT ? 2 : 3;
    EXPECT_TRUE(absl::StartsWith(p.address(), TestHosts::Address(host) + ":")) << p.id() << " at " << p.address();
  }
  EXPECT_TRUE(absl::StartsWith(endpoints_.world(), TestHosts::Hub() + ":")) << endpoints_.world();
  ASSERT_NO_FATAL_FAILURE(CheckTakeAndRefusals(certs.path()));

  // The controller's certificate renewed (same CA, new key): swapped in by rename, and presented to the next
  // connection without a restart.
  std::string before;
  ASSERT_TRUE(CallController(As(certs.path(), "operator-tester"), &before).ok());
  EXPECT_EQ(before, ReadFile(certs.path() + "/controller.crt"));
  TempDir renewed;
  for (const char* f : {"ca.crt", "ca.key"}) {
    std::filesystem::copy_file(certs.path() + "/" + f, renewed.path() + "/" + f);
  }
  CommandResult made = RunCommand({MakeTestCerts(), "--ip", TestHosts::Address(3), renewed.path(), "controller"},
                                  std::chrono::seconds(60));
  ASSERT_EQ(made.exit.exit_code, 0) << made.err;
  const std::string fresh = ReadFile(renewed.path() + "/controller.crt");
  ASSERT_NE(fresh, before);
  for (const char* f : {"controller.key", "controller.crt"}) {
    std::filesystem::copy_file(renewed.path() + "/" + f, certs.path() + "/" + f + ".new");
    std::filesystem::rename(certs.path() + "/" + f + ".new", certs.path() + "/" + f);
  }
  std::string after;
  for (int i = 0; i < 100 && after != fresh; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    after.clear();
    ASSERT_TRUE(CallController(As(certs.path(), "operator-tester"), &after).ok());
  }
  EXPECT_EQ(after, fresh) << "the controller still presents its old certificate";
  // The stage goes on with it: another take, COMPLETE.
  CommandResult again = Stagectl({"--as", "operator/tester", "capture", "--frames", "2", "--json"});
  ASSERT_EQ(again.exit.exit_code, 0) << again.err;
  EXPECT_EQ(nlohmann::json::parse(again.out)["outcome"], "TAKE_OUTCOME_COMPLETE");
}

}  // namespace
}  // namespace stage::testing

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  // Before any thread: the suite's own network namespace (its hosts' bridge lives there).
  stage::testing::g_why_not = stage::testing::IsolateNetwork(2, 2);
  return RUN_ALL_TESTS();
}
