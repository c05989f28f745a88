// One health poll as the controller makes it (grpc.health.v1 Check through a FaStage RpcServer on loopback, every call
// counted by the metrics interceptor), in plain text and over mutual TLS (certificates from scripts/make-test-certs,
// the call authorised by identity), next to its baseline in the same run: a bare TCP round trip of one byte over a
// loopback socket pair, the floor of any request/response on this machine.
// Run: build/bin/health_check_bench
#include <benchmark/benchmark.h>
#include <grpcpp/grpcpp.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <thread>

#include "grpc/health/v1/health.grpc.pb.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/v1/controller.grpc.pb.h"

namespace {

void BM_Baseline_TcpLoopbackRoundTrip(benchmark::State& state) {
  int listener = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  bind(listener, reinterpret_cast<sockaddr*>(&addr), sizeof(addr));
  listen(listener, 1);
  socklen_t len = sizeof(addr);
  getsockname(listener, reinterpret_cast<sockaddr*>(&addr), &len);
  std::thread echo([&] {
    int fd = accept(listener, nullptr, nullptr);
    int one = 1;
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
    char c;
    while (read(fd, &c, 1) == 1) {
      if (write(fd, &c, 1) != 1) break;
    }
    close(fd);
  });
  int client = socket(AF_INET, SOCK_STREAM, 0);
  connect(client, reinterpret_cast<sockaddr*>(&addr), sizeof(addr));
  int one = 1;
  setsockopt(client, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
  char c = 'x';
  for (auto _ : state) {
    if (write(client, &c, 1) != 1 || read(client, &c, 1) != 1) state.SkipWithError("socket failed");
  }
  close(client);
  echo.join();
  close(listener);
}
BENCHMARK(BM_Baseline_TcpLoopbackRoundTrip)->Unit(benchmark::kMicrosecond)->UseRealTime();

void BM_HealthCheckThroughRpcServer(benchmark::State& state) {
  stage::v1::StageController::Service service;
  auto server = stage::RpcServer::Start({.listen = "127.0.0.1:0"}, {&service});
  if (!server.ok()) {
    state.SkipWithError("server did not start");
    return;
  }
  auto stub = grpc::health::v1::Health::NewStub(stage::MakeChannel((*server)->address()));
  for (auto _ : state) {
    grpc::ClientContext context;
    grpc::health::v1::HealthCheckResponse response;
    grpc::Status s = stub->Check(&context, grpc::health::v1::HealthCheckRequest(), &response);
    if (!s.ok()) state.SkipWithError(s.error_message().c_str());
  }
}
BENCHMARK(BM_HealthCheckThroughRpcServer)->Unit(benchmark::kMicrosecond)->UseRealTime();

// The same poll over mutual TLS on one open connection: what encryption and the per-call authorisation add.
void BM_HealthCheckOverMutualTls(benchmark::State& state) {
  const std::string dir = "/tmp/health_check_bench." + std::to_string(getpid());
  const std::string make = std::string(FASTAGE_SOURCE_DIR) + "/scripts/make-test-certs " + dir +
                           " light/L1 controller > /dev/null";
  if (std::system(make.c_str()) != 0) {
    state.SkipWithError("scripts/make-test-certs failed");
    return;
  }
  auto as = [&](const std::string& file) {
    return stage::TransportSecurity{.mode = stage::TransportSecurity::Mode::kMutualTls,
                                    .ca_file = dir + "/ca.crt",
                                    .cert_file = dir + "/" + file + ".crt",
                                    .key_file = dir + "/" + file + ".key"};
  };
  const stage::TransportSecurity light = as("light-L1");
  stage::v1::StageController::Service service;
  auto server = stage::RpcServer::Start({.listen = "127.0.0.1:0", .security = &light}, {&service});
  if (!server.ok()) {
    state.SkipWithError("server did not start");
    return;
  }
  auto stub = grpc::health::v1::Health::NewStub(
      stage::MakeChannel((*server)->address(), grpc::ChannelArguments(), as("controller")));
  for (auto _ : state) {
    grpc::ClientContext context;
    grpc::health::v1::HealthCheckResponse response;
    grpc::Status s = stub->Check(&context, grpc::health::v1::HealthCheckRequest(), &response);
    if (!s.ok()) state.SkipWithError(s.error_message().c_str());
  }
  server->reset();
  std::filesystem::remove_all(dir);
}
BENCHMARK(BM_HealthCheckOverMutualTls)->Unit(benchmark::kMicrosecond)->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
