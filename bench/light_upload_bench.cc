// Uploading and verifying the shipped rig's 38-pattern tables on every Modbus light node (four 64-channel boards,
// fake boards on loopback TCP), with the light node's driver: 0x17 blocks written and read back at once, limits,
// commit with the board's CRC. Beside it, in the same run and against the same boards: the baseline, a loop of
// single-register writes (0x06) of the same tables, and that loop with a read-back of each register (0x03), which is
// what "upload and verify" costs without block transfers. Goal (issue #8): all nodes in < 100 ms.
// The rig's two gpiod nodes hold their tables in the node's memory (no bus), so they are not part of the figure.
// Run: build/bin/light_upload_bench [--rounds 5]
#include <modbus/modbus.h>

#include <chrono>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "bench_util.h"
#include "modbus_light_driver.h"
#include "stage/light/led_board_map.h"
#include "stage/sim/fake_led_board.h"
#include "stage/sim/world_devices.h"

namespace {

using stage::bench::Clock;
using stage::bench::Median;
using stage::bench::Ms;
[[noreturn]] void Die(const std::string& what) { stage::bench::Die("light_upload_bench", what); }

struct Node {
  stage::v1::LightNodeConfig config;
  stage::light::PatternTable table;
  std::unique_ptr<stage::sim::FakeLedBoard> board;
};

// The baseline on one board: every register of the table by 0x06, optionally each read back by 0x03.
double SingleRegisterLoop(const Node& n, bool verify) {
  modbus_t* ctx = modbus_new_tcp("127.0.0.1", n.board->port());
  if (ctx == nullptr || modbus_connect(ctx) != 0) Die("baseline: cannot connect");
  modbus_set_slave(ctx, 1);
  const uint32_t channels = n.config.channel_count();
  const auto start = Clock::now();
  for (size_t r = 0; r < n.table.rows.size(); ++r) {
    for (uint32_t c = 0; c < channels; ++c) {
      const int address = stage::light::board::TableAddress(static_cast<uint32_t>(r), c, channels);
      if (modbus_write_register(ctx, address, n.table.rows[r][c]) != 1) Die("baseline: write failed");
      if (verify) {
        uint16_t back = 0;
        if (modbus_read_registers(ctx, address, 1, &back) != 1 || back != n.table.rows[r][c]) {
          Die("baseline: read-back failed");
        }
      }
    }
  }
  const double ms = Ms(Clock::now() - start);
  modbus_close(ctx);
  modbus_free(ctx);
  return ms;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Upload and verify of the shipped rig's pattern tables on its Modbus light nodes (fake boards on "
               "loopback), beside a single-register write loop.",
               "light_upload_bench"};
  int rounds = 5;
  app.add_option("--rounds", rounds, "rounds; the median is reported")->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  const stage::bench::ShippedRig shipped = stage::bench::LoadShippedRig("light_upload_bench");

  std::vector<Node> nodes;
  for (int i = 0; i < shipped.rig.rig.light_nodes_size(); ++i) {
    const auto& config = shipped.rig.rig.light_nodes(i);
    if (config.backend() != stage::v1::LIGHT_BACKEND_MODBUS) continue;
    Node n;
    n.config = config;
    n.table = stage::sim::TableFromSchedule(shipped.schedule.light_nodes(i));
    auto board = stage::sim::FakeLedBoard::StartFor(&n.config);
    if (!board.ok()) Die(std::string(board.status().message()));
    n.board = std::move(*board);
    nodes.push_back(std::move(n));
  }
  std::vector<std::unique_ptr<stage::light::ModbusLightDriver>> drivers;
  for (const Node& n : nodes) {
    auto options = stage::light::ModbusDriverOptionsFromRig(n.config);
    if (!options.ok()) Die(std::string(options.status().message()));
    auto d = stage::light::ModbusLightDriver::Open(*options);
    if (!d.ok()) Die(std::string(d.status().message()));
    drivers.push_back(std::move(*d));
  }
  size_t registers = 0;
  for (const Node& n : nodes) registers += n.table.rows.size() * n.config.channel_count();
  std::printf("%zu Modbus light nodes, %zu rows x %u channels each, %zu table registers in all; %d rounds\n",
              nodes.size(), nodes.front().table.rows.size(), nodes.front().config.channel_count(), registers, rounds);

  std::vector<double> serial, parallel, write_loop, verify_loop;
  uint64_t transactions = 0;
  for (int r = 0; r < rounds; ++r) {
    // The driver, node after node (as one controller thread would arm them).
    uint64_t before = 0;
    for (const auto& d : drivers) before += d->transactions();
    auto start = Clock::now();
    for (size_t i = 0; i < nodes.size(); ++i) {
      if (auto s = drivers[i]->LoadPatternTable(nodes[i].table); !s.ok()) Die(std::string(s.message()));
    }
    serial.push_back(Ms(Clock::now() - start));
    uint64_t after = 0;
    for (const auto& d : drivers) after += d->transactions();
    transactions = after - before;
    // All nodes at once (each light node uploads its own board).
    start = Clock::now();
    std::vector<std::thread> threads;
    for (size_t i = 0; i < nodes.size(); ++i) {
      threads.emplace_back([&, i] {
        if (auto s = drivers[i]->LoadPatternTable(nodes[i].table); !s.ok()) Die(std::string(s.message()));
      });
    }
    for (auto& t : threads) t.join();
    parallel.push_back(Ms(Clock::now() - start));
    // Baselines, node after node.
    double w = 0, v = 0;
    for (const Node& n : nodes) w += SingleRegisterLoop(n, false);
    for (const Node& n : nodes) v += SingleRegisterLoop(n, true);
    write_loop.push_back(w);
    verify_loop.push_back(v);
  }
  const double s = Median(serial), p = Median(parallel), w = Median(write_loop), v = Median(verify_loop);
  std::printf("%-58s %10s %14s\n", "", "median ms", "transactions");
  std::printf("%-58s %10.2f %14llu\n", "driver: upload + verify, node after node", s,
              static_cast<unsigned long long>(transactions));
  std::printf("%-58s %10.2f %14llu\n", "driver: upload + verify, all nodes at once", p,
              static_cast<unsigned long long>(transactions));
  std::printf("%-58s %10.2f %14zu\n", "baseline: single-register write loop (0x06), no verify", w, registers);
  std::printf("%-58s %10.2f %14zu\n", "baseline: single-register write + read-back loop", v, 2 * registers);
  std::printf("driver (node after node) vs write loop: %.1fx faster, vs write + read-back loop: %.1fx; goal < 100 ms: "
              "%s\n",
              w / s, v / s, s < 100 ? "met" : "NOT met");
  return 0;
}
