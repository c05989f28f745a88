// A simulated LED driver board on a real Modbus link: a libmodbus server implementing the board's register map
// (docs/led-board-modbus.md) over TCP or over RTU (a serial device, in tests one end of a pseudo-terminal pair made by
// socat). Its LEDs are a SimLightDriver: the board steps it on slot-clock edges (Step(), or the world's clock once
// attached), so a board in the simulated stage lights the world as the sim backend does.
//
// Fault knobs: no answer (requests are read and dropped), a corrupted table entry (the cell keeps a flipped bit, so
// it reads back wrong), over temperature (the board blacks out and refuses to leave blackout). Every request is
// logged (function, address, count) for tests that check what went over the bus. No libmodbus header appears here.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/sim/sim_light_driver.h"

namespace stage::sim {

class SimScene;
class WorldClient;
}  // namespace stage::sim

namespace stage::v1 {
class LightNodeConfig;
}  // namespace stage::v1

namespace stage::sim {

struct FakeLedBoardOptions {
  // Name in logs and errors (the light node it stands for).
  std::string board_id = "fake-board";
  // Channels, 1..64; table capacity, rows.
  uint32_t channel_count = 64;
  uint32_t max_rows = 64;
  // Modbus unit (slave) id the board answers on RTU (TCP answers any). 1..247.
  int unit_id = 1;
  // Transport: a TCP listener (host, port; port 0 picks a free one) or an RTU serial device. Exactly one.
  std::string tcp_host;
  int tcp_port = 0;
  std::string rtu_device;
  int rtu_baud = 115200;
  char rtu_parity = 'N';
  int rtu_data_bits = 8;
  int rtu_stop_bits = 1;
  // Serial number and board temperature, degC; above the limit the board blacks out.
  uint32_t serial = 1;
  double temperature_c = 31.5;
  double temperature_limit_c = 70.0;

  absl::Status Validate() const;
};

// A request as the board received it.
struct BoardRequest {
  int function = 0;
  uint16_t address = 0;  // first register (the read's for 0x03; the write's for 0x06, 0x10 and 0x17)
  uint16_t count = 0;
  uint16_t read_address = 0;  // 0x17 only
  uint16_t read_count = 0;
  bool answered = false;
  int64_t at_ns = 0;  // steady clock
};

// The board of a modbus light node: the node's channel count and unit id, TCP on 127.0.0.1 at a free port, serial
// number `serial`. InvalidArgument names the node when it is not a modbus node of 1..64 channels.
absl::StatusOr<FakeLedBoardOptions> FakeLedBoardOptionsForNode(const v1::LightNodeConfig& node, uint32_t serial = 1);

class FakeLedBoard {
 public:
  // Listens (TCP) or opens the serial device (RTU) and serves from a thread of its own until destroyed.
  static absl::StatusOr<std::unique_ptr<FakeLedBoard>> Start(FakeLedBoardOptions options);
  // A board for modbus light node `node` (FakeLedBoardOptionsForNode), with the node's modbus.tcp pointed at it.
  static absl::StatusOr<std::unique_ptr<FakeLedBoard>> StartFor(v1::LightNodeConfig* node);
  ~FakeLedBoard();

  // "tcp://127.0.0.1:40211" or "rtu:/dev/pts/4".
  std::string endpoint() const;
  // The TCP port listened on (0 for RTU).
  int port() const;
  const FakeLedBoardOptions& options() const;

  // The board's LEDs: step them (a slot-clock edge), read their outputs, or attach them to the world.
  SimLightDriver& leds();

  // In the simulated stage (sim.modbus_fakes): the board's LEDs join `world` as light node `node_id` (not armed: the
  // node arms the board over Modbus) and the rig's board faults for the node (sim.faults board_silent_at_s) apply on
  // the world's clock.
  // With `arm` (a world without takes), the LEDs are armed with the node's table from the schedule at once.
  absl::Status JoinStage(const SimScene& scene, const std::string& node_id, WorldClient* world, bool arm = false);

  // Fault knobs (thread-safe, take effect at the next request).
  void SetNoAnswer(bool on);
  // Silent now; answers again at the first request after `wall` has passed.
  void SetNoAnswerFor(std::chrono::milliseconds wall);
  // The cell of (row, channel) keeps its value with bit 8 flipped; row < 0 clears the fault.
  void SetCorruptEntry(int row, int channel);
  // Over temperature now: temperature above the limit, blackout latched with the over-temperature fault.
  void SetOverTemperature(bool on);

  // Requests since the last ClearRequests().
  std::vector<BoardRequest> Requests() const;
  void ClearRequests();

  class Impl;

 private:
  explicit FakeLedBoard(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stage::sim
