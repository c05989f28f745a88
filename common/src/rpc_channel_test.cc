// Mutual TLS on loopback with certificates from scripts/make-test-certs: who may call what, what is refused, a
// certificate replaced on disk used without a restart, and the start-up checks of the files.
#include "stage/common/rpc_channel.h"

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <thread>

#include "gmock/gmock.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "gtest/gtest.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/rpc_server.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage {
namespace {

using ::testing::HasSubstr;
namespace fs = std::filesystem;

// A temporary directory of certificates: `ca` signs every identity given.
class Certs {
 public:
  explicit Certs(const std::string& name, const std::vector<std::string>& identities)
      : dir_(fs::temp_directory_path() / ("rpc_channel_test." + std::to_string(getpid()) + "." + name)) {
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    if (!identities.empty()) Make(identities);
  }
  ~Certs() { fs::remove_all(dir_); }
  void Make(const std::vector<std::string>& identities) const {
    std::string command = std::string(FASTAGE_SOURCE_DIR) + "/scripts/make-test-certs " + dir_.string();
    for (const auto& id : identities) command += " " + id;
    ASSERT_EQ(std::system((command + " > /dev/null").c_str()), 0) << command;
  }
  TransportSecurity As(const std::string& identity, int reload_s = 5) const {
    std::string file = identity;
    for (char& c : file) c = c == '/' ? '-' : c;
    return {.mode = TransportSecurity::Mode::kMutualTls,
            .ca_file = (dir_ / "ca.crt").string(),
            .cert_file = (dir_ / (file + ".crt")).string(),
            .key_file = (dir_ / (file + ".key")).string(),
            .reload_interval_s = reload_s};
  }
  const fs::path& dir() const { return dir_; }

 private:
  fs::path dir_;
};

v1::LightNode::Service g_light;  // unimplemented: a call that reaches it was authorised

grpc::Status CallLight(const std::string& address, const TransportSecurity& as, int attempt = 0) {
  grpc::ChannelArguments args;
  args.SetInt("fastage.test.attempt", attempt);  // a channel of its own, not a shared connection
  auto stub = v1::LightNode::NewStub(MakeChannel(address, args, as));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
  v1::NodeInfo info;
  return stub->GetInfo(&context, v1::GetInfoRequest(), &info);
}

TEST(RpcChannelTest, TheControllerDrivesALightNodeACameraIsRefusedEveryoneChecksHealth) {
  Certs certs("roles", {"light/L1", "controller", "camera/mv-01"});
  const TransportSecurity light = certs.As("light/L1");
  auto server = RpcServer::Start({.listen = "127.0.0.1:0", .security = &light}, {&g_light});
  ASSERT_TRUE(server.ok()) << server.status();
  // Authorised: the call reaches the (unimplemented) handler.
  EXPECT_EQ(CallLight((*server)->address(), certs.As("controller")).error_code(), grpc::StatusCode::UNIMPLEMENTED);
  const grpc::Status camera = CallLight((*server)->address(), certs.As("camera/mv-01"));
  EXPECT_EQ(camera.error_code(), grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(camera.error_message(),
            "camera/mv-01 may not call /stage.v1.LightNode/GetInfo: stage.v1.LightNode takes calls from controller "
            "only");
  auto health = grpc::health::v1::Health::NewStub(
      MakeChannel((*server)->address(), grpc::ChannelArguments(), certs.As("camera/mv-01")));
  grpc::ClientContext context;
  grpc::health::v1::HealthCheckResponse response;
  ASSERT_TRUE(health->Check(&context, grpc::health::v1::HealthCheckRequest(), &response).ok());
  EXPECT_EQ(response.status(), grpc::health::v1::HealthCheckResponse::SERVING);
}

TEST(RpcChannelTest, AnotherCasCertificateAndAPlainTextClientAreRefused) {
  Certs certs("stage", {"light/L1", "controller"});
  Certs other("other", {"controller"});
  const TransportSecurity light = certs.As("light/L1");
  auto server = RpcServer::Start({.listen = "127.0.0.1:0", .security = &light}, {&g_light});
  ASSERT_TRUE(server.ok()) << server.status();
  ASSERT_TRUE(InitLogging("rpc_channel_test", "").ok());  // gRPC's words through the processes' logging
  ::testing::internal::CaptureStderr();
  const grpc::Status foreign = CallLight((*server)->address(), other.As("controller"));
  const grpc::Status plain = CallLight((*server)->address(), TransportSecurity());
  // The refusing side logs before it closes the connection the client saw closed.
  const std::string log = ::testing::internal::GetCapturedStderr();
  EXPECT_EQ(foreign.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ(plain.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(log, HasSubstr("rpc.tls: refused a connection: TLS handshake failed: the peer's certificate is not "
                             "signed by this stage's CA"));
  EXPECT_THAT(log, HasSubstr("rpc.tls: refused a connection: TLS handshake failed: the peer does not speak TLS"));
  EXPECT_EQ(CallLight((*server)->address(), certs.As("controller")).error_code(), grpc::StatusCode::UNIMPLEMENTED);
}

TEST(RpcChannelTest, AReplacedCertificateIsUsedWithoutARestart) {
  Certs certs("reload", {"light/L1", "controller"});
  const TransportSecurity light = certs.As("light/L1", /*reload_s=*/1);
  auto server = RpcServer::Start({.listen = "127.0.0.1:0", .security = &light}, {&g_light});
  ASSERT_TRUE(server.ok()) << server.status();
  // The server's certificate as a new connection sees it.
  auto served = [&](int attempt) {
    grpc::ChannelArguments args;
    args.SetInt("fastage.test.attempt", attempt);
    auto stub = v1::LightNode::NewStub(MakeChannel((*server)->address(), args, certs.As("controller")));
    grpc::ClientContext context;
    v1::NodeInfo info;
    (void)stub->GetInfo(&context, v1::GetInfoRequest(), &info);
    auto pem = context.auth_context()->FindPropertyValues("x509_pem_cert");
    return pem.empty() ? std::string() : std::string(pem[0].data(), pem[0].size());
  };
  const std::string before = served(0);
  ASSERT_FALSE(before.empty());
  // A new certificate for the same identity, put in place by rename (the key first: both are read each interval).
  Certs fresh("reload-new", {});
  fs::copy_file(certs.dir() / "ca.crt", fresh.dir() / "ca.crt");
  fs::copy_file(certs.dir() / "ca.key", fresh.dir() / "ca.key");
  fresh.Make({"light/L1"});
  fs::rename(fresh.dir() / "light-L1.key", certs.dir() / "light-L1.key");
  fs::rename(fresh.dir() / "light-L1.crt", certs.dir() / "light-L1.crt");
  const std::string after = ReadFileToString((certs.dir() / "light-L1.crt").string()).value_or("");
  ASSERT_NE(after, before);
  std::string now = before;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  for (int attempt = 1; now != after && std::chrono::steady_clock::now() < deadline; ++attempt) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    now = served(attempt);
  }
  EXPECT_EQ(now, after) << "the server still serves its old certificate";
}

TEST(RpcChannelTest, TheFilesAreCheckedAtStartUpNamingTheFile) {
  Certs certs("check", {"light/L1", "controller"});
  Certs other("check-other", {"light/L1"});
  TransportSecurity s = certs.As("light/L1");
  EXPECT_TRUE(s.Validate().ok()) << s.Validate();
  s.cert_file = "/nonexistent.crt";
  EXPECT_THAT(s.Validate().message(), HasSubstr("cert_file: cannot read /nonexistent.crt"));
  s = certs.As("light/L1");
  s.key_file = certs.As("controller").key_file;
  EXPECT_THAT(s.Validate().message(), HasSubstr("is not the key of the certificate"));
  s = other.As("light/L1");
  s.ca_file = certs.As("light/L1").ca_file;
  EXPECT_THAT(s.Validate().message(), HasSubstr("does not verify against the CA"));
  s = certs.As("light/L1");
  s.ca_file = s.key_file;
  EXPECT_THAT(s.Validate().message(), HasSubstr("ca_file: " + s.key_file + " holds no PEM certificate"));
  EXPECT_THAT(TransportSecurity{.ca_file = "x"}.Validate().message(), HasSubstr("plain text takes no certificate"));
  EXPECT_FALSE(SetTransportSecurity(other.As("light/L1", 0)).ok());
  EXPECT_EQ(DescribeTransportSecurity(), "plain text, loopback only");
}

TEST(RpcChannelTest, WhoMayCallWhat) {
  std::string why;
  EXPECT_TRUE(AuthorizeCall("controller", "/stage.v1.LightNode/Arm", &why));
  EXPECT_FALSE(AuthorizeCall("camera/mv-01", "/stage.v1.LightNode/Arm", &why));
  EXPECT_EQ(why, "stage.v1.LightNode takes calls from controller only");
  EXPECT_TRUE(AuthorizeCall("operator/ana", "/stage.v1.StageController/Capture", &why));
  EXPECT_TRUE(AuthorizeCall("observer/bo", "/stage.v1.StageController/GetStageStatus", &why));
  EXPECT_TRUE(AuthorizeCall("observer/bo", "/stage.v1.StageController/WatchStageStatus", &why));
  EXPECT_FALSE(AuthorizeCall("observer/bo", "/stage.v1.StageController/Capture", &why));
  EXPECT_EQ(why, "stage.v1.StageController (its commands) takes calls from operator, console only");
  // The console commands the stage for its users (it checks their roles), and drives no node.
  EXPECT_TRUE(AuthorizeCall("console", "/stage.v1.StageController/EmergencyStop", &why));
  EXPECT_TRUE(AuthorizeCall("console", "/stage.v1.StageController/WatchStageStatus", &why));
  EXPECT_FALSE(AuthorizeCall("console", "/stage.v1.LightNode/Blackout", &why));
  EXPECT_FALSE(AuthorizeCall("console/x", "/stage.v1.StageController/Capture", &why));
  EXPECT_TRUE(AuthorizeCall("operator/ana", "/stage.v1.CameraNode/GetStats", &why));
  EXPECT_FALSE(AuthorizeCall("operator/ana", "/stage.v1.CameraNode/Arm", &why));
  EXPECT_FALSE(AuthorizeCall("worker/w1", "/stage.v1.StageController/GetStageStatus", &why));
  EXPECT_TRUE(AuthorizeCall("camera/mv-01", "/stage.v1.SimWorld/Join", &why));
  EXPECT_TRUE(AuthorizeCall("light/L1", "/stage.v1.SimWorld/Run", &why));
  EXPECT_FALSE(AuthorizeCall("camera/mv-01", "/stage.v1.SimWorld/WriteGroundTruth", &why));
  EXPECT_FALSE(AuthorizeCall("light/L1", "/stage.v1.SimWorld/InjectFault", &why));
  EXPECT_TRUE(AuthorizeCall("operator/ana", "/stage.v1.SimWorld/InjectFault", &why));
  // An identity is a whole name, not a prefix.
  EXPECT_FALSE(AuthorizeCall("controller/x", "/stage.v1.LightNode/Arm", &why));
  EXPECT_THAT(why, HasSubstr("not a FaStage identity"));
  EXPECT_FALSE(AuthorizeCall("camera/", "/stage.v1.SimWorld/Join", &why));
  EXPECT_TRUE(AuthorizeCall("light/L1", "/grpc.health.v1.Health/Check", &why));
  EXPECT_FALSE(AuthorizeCall("controller", "/other.Service/Call", &why));
  EXPECT_THAT(why, HasSubstr("not a FaStage service"));
  EXPECT_FALSE(AuthorizeCall("", "/grpc.health.v1.Health/Check", &why));
  EXPECT_EQ(why, "the peer presented no certificate");
}

TEST(RpcServerLoopbackTest, OnlyLoopbackAddressesAreLoopback) {
  for (const char* host : {"127.0.0.1", "127.8.9.10", "localhost", "::1", "[::1]", "::ffff:127.0.0.1"}) {
    EXPECT_TRUE(IsLoopbackHost(host)) << host;
  }
  for (const char* host : {"0.0.0.0", "10.0.0.2", "::", "127.attacker.example", "example.org", "128.0.0.1", ""}) {
    EXPECT_FALSE(IsLoopbackHost(host)) << host;
  }
}

}  // namespace
}  // namespace stage
