// RpcServer on a real socket: port 0 is resolved, the health service answers, shutdown flips it, a taken port is an
// error naming the address.
#include "stage/common/rpc_server.h"

#include <grpcpp/grpcpp.h>

#include <fstream>

#include "gmock/gmock.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "gtest/gtest.h"
#include "stage/v1/controller.grpc.pb.h"

namespace stage {
namespace {

using ::testing::HasSubstr;

// gRPC needs at least one service to build a server; any generated service does.
v1::StageController::Service g_service;

grpc::health::v1::HealthCheckResponse::ServingStatus Check(const std::string& address, grpc::Status* rpc) {
  auto stub = grpc::health::v1::Health::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
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
