// RpcServer on a real socket: port 0 is resolved, the health service answers, shutdown flips it, a taken port is an
// error naming the address.
#include "stage/common/rpc_server.h"

#include <grpcpp/grpcpp.h>

#include <fstream>

#include "gmock/gmock.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "gtest/gtest.h"
#include "stage/common/metrics.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/controller.grpc.pb.h"

namespace stage {
namespace {

using ::testing::HasSubstr;

// gRPC needs at least one service to build a server; any generated service does.
v1::StageController::Service g_service;

grpc::health::v1::HealthCheckResponse::ServingStatus Check(const std::string& address, grpc::Status* rpc) {
  auto stub = grpc::health::v1::Health::NewStub(MakeChannel(address));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  grpc::health::v1::HealthCheckResponse response;
  *rpc = stub->Check(&context, grpc::health::v1::HealthCheckRequest(), &response);
  return response.status();
}

TEST(RpcServerTest, PortZeroBindsAFreePortAndServesHealth) {
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&g_service});
  ASSERT_TRUE(server.ok()) << server.status();
  EXPECT_GT((*server)->port(), 0);
  EXPECT_EQ((*server)->address(), "127.0.0.1:" + std::to_string((*server)->port()));
  grpc::Status rpc;
  EXPECT_EQ(Check((*server)->address(), &rpc), grpc::health::v1::HealthCheckResponse::SERVING);
  EXPECT_TRUE(rpc.ok()) << rpc.error_message();
  (*server)->SetServing(false);
  EXPECT_EQ(Check((*server)->address(), &rpc), grpc::health::v1::HealthCheckResponse::NOT_SERVING);
}

TEST(RpcServerTest, PortInUseIsAnErrorNamingTheAddress) {
  auto first = RpcServer::Start({.listen = "127.0.0.1:0"}, {&g_service});
  ASSERT_TRUE(first.ok());
  auto second = RpcServer::Start({.listen = (*first)->address()}, {&g_service});
  ASSERT_FALSE(second.ok());
  EXPECT_THAT(std::string(second.status().message()), HasSubstr("cannot listen on " + (*first)->address()));
}

TEST(RpcServerTest, OptionsAreValidated) {
  EXPECT_FALSE(RpcServerOptions{.listen = "nowhere"}.Validate().ok());
  EXPECT_FALSE((RpcServerOptions{.listen = "127.0.0.1:0", .max_message_bytes = 10}.Validate().ok()));
  EXPECT_TRUE(RpcServerOptions{}.Validate().ok());
}

TEST(RpcServerTest, AfterShutdownNothingAnswers) {
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&g_service});
  ASSERT_TRUE(server.ok());
  std::string address = (*server)->address();
  (*server)->Shutdown();
  grpc::Status rpc;
  Check(address, &rpc);
  EXPECT_FALSE(rpc.ok());
}

TEST(RpcServerTest, EveryCallIsCountedAndTimedByMethodAndCode) {
  metrics::Registry registry;
  auto server = RpcServer::Start({.listen = "127.0.0.1:0", .metrics = &registry}, {&g_service});
  ASSERT_TRUE(server.ok()) << server.status();
  grpc::Status rpc;
  Check((*server)->address(), &rpc);
  Check((*server)->address(), &rpc);
  // The bare service answers Unimplemented: a failure is handled too, under its code.
  auto stub = v1::StageController::NewStub(MakeChannel((*server)->address()));
  grpc::ClientContext context;
  v1::NodeInfo info;
  EXPECT_EQ(stub->GetInfo(&context, v1::GetInfoRequest(), &info).error_code(), grpc::StatusCode::UNIMPLEMENTED);
  const std::string text = registry.Render();
  const std::string check = "grpc_type=\"unary\",grpc_service=\"grpc.health.v1.Health\",grpc_method=\"Check\"";
  EXPECT_THAT(text, HasSubstr("grpc_server_started_total{" + check + "} 2\n")) << text;
  EXPECT_THAT(text, HasSubstr("grpc_server_handled_total{" + check + ",grpc_code=\"OK\"} 2\n")) << text;
  EXPECT_THAT(text, HasSubstr("grpc_server_handling_seconds_count{" + check + "} 2\n")) << text;
  EXPECT_THAT(text, HasSubstr("grpc_server_handled_total{grpc_type=\"unary\",grpc_service=\"stage.v1.StageController\","
                              "grpc_method=\"GetInfo\",grpc_code=\"Unimplemented\"} 1\n"))
      << text;
}

TEST(RpcServerTest, AddressFileIsWrittenWhole) {
  std::string path = "/tmp/fastage-rpc-test.addr";
  ASSERT_TRUE(WriteAddressFile(path, "127.0.0.1:1234").ok());
  std::ifstream in(path);
  std::string line;
  std::getline(in, line);
  EXPECT_EQ(line, "127.0.0.1:1234");
  std::remove(path.c_str());
  EXPECT_FALSE(WriteAddressFile("/nonexistent/dir/x.addr", "a:1").ok());
}

}  // namespace
}  // namespace stage
