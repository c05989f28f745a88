// The emergency stop of the shipped rig, in one process on loopback: six light nodes with their services (the four
// Modbus nodes on fake LED boards through the real Modbus backend, the two others on the sim backend), armed with
// their take tables, and the controller's EmergencyStop telling all of them to black out at once and waiting for every
// confirmation. Beside it, in the same run and over the same channels: the gRPC floor (the same fan-out of a GetInfo
// to every node, one thread each, as the stop does it) and the Modbus floor (one register write to a fake board,
// what the board's blackout costs on the bus). The stop cannot beat the sum of the two; what it adds is its own.
// Run: build/bin/estop_bench [--rounds 50]
#include <grpcpp/grpcpp.h>
#include <modbus/modbus.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <thread>

#include "CLI/CLI.hpp"
#include "bench_util.h"
#include "emergency_stop.h"
#include "light_node.h"
#include "light_service.h"
#include "modbus_light_driver.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/light/led_board_map.h"
#include "stage/sim/fake_led_board.h"
#include "stage/sim/sim_light_driver.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace {

using stage::bench::Clock;
using stage::bench::Median;
using stage::bench::Ms;
[[noreturn]] void Die(const std::string& what) { stage::bench::Die("estop_bench", what); }

struct Node {
  std::unique_ptr<stage::sim::FakeLedBoard> board;
  std::unique_ptr<stage::light::LightNode> node;
  std::unique_ptr<stage::light::LightService> service;
  std::unique_ptr<stage::RpcServer> server;
  stage::v1::ArmLightRequest arm;
};

double Max(const std::vector<double>& v) { return *std::max_element(v.begin(), v.end()); }

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"The shipped rig's emergency stop on loopback (six light nodes, four on fake Modbus boards), beside "
               "a gRPC fan-out to the same nodes and a single Modbus register write.",
               "estop_bench"};
  int rounds = 50;
  app.add_option("--rounds", rounds, "stops (each after arming every node); median and worst are reported")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  CLI11_PARSE(app, argc, argv);

  const stage::bench::ShippedRig shipped = stage::bench::LoadShippedRig("estop_bench");
  stage::v1::RigConfig live = shipped.rig.rig;
  std::vector<Node> nodes(static_cast<size_t>(live.light_nodes_size()));
  int modbus_nodes = 0;
  for (int i = 0; i < live.light_nodes_size(); ++i) {
    stage::v1::LightNodeConfig& config = *live.mutable_light_nodes(i);
    Node& n = nodes[static_cast<size_t>(i)];
    std::unique_ptr<stage::light::LightDriver> driver;
    if (config.backend() == stage::v1::LIGHT_BACKEND_MODBUS) {
      auto board = stage::sim::FakeLedBoard::StartFor(&config);
      if (!board.ok()) Die(std::string(board.status().message()));
      n.board = std::move(*board);
      auto options = stage::light::ModbusDriverOptionsFromRig(config);
      if (!options.ok()) Die(std::string(options.status().message()));
      auto d = stage::light::ModbusLightDriver::Open(*options);
      if (!d.ok()) Die(std::string(d.status().message()));
      driver = std::move(*d);
      ++modbus_nodes;
    } else {
      driver = std::make_unique<stage::sim::SimLightDriver>(config.id(), config.channel_count());
    }
    stage::light::LightNodeOptions node_options;
    node_options.slot_rate_hz = live.timing().slot_rate_hz();
    node_options.take_length_s = live.timing().take_length_s();
    auto node = stage::light::LightNode::Create(config, std::move(driver), "bench", node_options);
    if (!node.ok()) Die(std::string(node.status().message()));
    n.node = std::move(*node);
    n.service = std::make_unique<stage::light::LightService>(n.node.get());
    auto server = stage::RpcServer::Start({}, {n.service.get()});
    if (!server.ok()) Die(std::string(server.status().message()));
    n.server = std::move(*server);
    config.set_address(n.server->address());
    n.arm.set_take_id("bench");
    *n.arm.mutable_table() = shipped.schedule.light_nodes(i).table();
    n.arm.set_heartbeat_timeout_ms(600'000);
  }

  stage::controller::EmergencyStop estop(live);
  std::vector<std::shared_ptr<grpc::Channel>> channels;
  for (const auto& n : nodes) {
    channels.push_back(stage::MakeChannel(n.server->address()));
  }
  auto arm_all = [&] {
    for (auto& n : nodes) {
      if (auto s = n.node->Arm(n.arm); !s.ok()) Die(std::string(s.message()));
    }
  };
  auto fan_out = [&] {
    const auto start = Clock::now();
    std::vector<std::thread> threads;
    for (auto& channel : channels) {
      threads.emplace_back([&channel] {
        auto stub = stage::v1::LightNode::NewStub(channel);
        grpc::ClientContext context;
        context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
        stage::v1::NodeInfo info;
        if (!stub->GetInfo(&context, stage::v1::GetInfoRequest(), &info).ok()) Die("GetInfo failed");
      });
    }
    for (auto& t : threads) t.join();
    return Ms(Clock::now() - start);
  };
  // The Modbus floor: one register write (the mode register, to idle: harmless) to the first board.
  const stage::sim::FakeLedBoard* first_board = nullptr;
  for (const auto& n : nodes) {
    if (n.board != nullptr && first_board == nullptr) first_board = n.board.get();
  }
  if (first_board == nullptr) Die("the rig has no Modbus light node");
  modbus_t* ctx = modbus_new_tcp("127.0.0.1", first_board->port());
  if (ctx == nullptr || modbus_connect(ctx) != 0) Die("modbus baseline: cannot connect");

  // Warm-up: connections made, code paged in.
  arm_all();
  estop.Stop("warm-up");
  if (auto r = estop.Reset(); !r.ok()) Die(std::string(r.status().message()));
  fan_out();

  std::vector<double> stop_ms, fan_out_ms, write_ms;
  for (int r = 0; r < rounds; ++r) {
    arm_all();
    stage::v1::EmergencyStopReply reply = estop.Stop("bench");
    if (!reply.all_dark()) Die("a node did not confirm dark: " + reply.ShortDebugString());
    stop_ms.push_back(reply.elapsed_ms());
    if (auto reset = estop.Reset(); !reset.ok()) Die(std::string(reset.status().message()));
    fan_out_ms.push_back(fan_out());
    const auto start = Clock::now();
    if (modbus_write_register(ctx, stage::light::board::kMode, 0) != 1) Die("modbus baseline: write failed");
    write_ms.push_back(Ms(Clock::now() - start));
  }
  modbus_close(ctx);
  modbus_free(ctx);

  std::printf("%zu light nodes (%d on fake Modbus boards), armed with their take tables; %d stops\n", nodes.size(),
              modbus_nodes, rounds);
  std::printf("%-62s %10s %10s\n", "", "median ms", "worst ms");
  std::printf("%-62s %10.3f %10.3f\n", "emergency stop: request to every node confirmed dark", Median(stop_ms),
              Max(stop_ms));
  std::printf("%-62s %10.3f %10.3f\n", "baseline: gRPC fan-out, GetInfo to every node (one thread each)",
              Median(fan_out_ms), Max(fan_out_ms));
  std::printf("%-62s %10.3f %10.3f\n", "baseline: one Modbus register write to a fake board", Median(write_ms),
              Max(write_ms));
  std::printf("the stop's own cost over the two floors: %.3f ms (median)\n",
              Median(stop_ms) - Median(fan_out_ms) - Median(write_ms));
  return 0;
}
