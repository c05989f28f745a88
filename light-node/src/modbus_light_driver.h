// LED driver boards over Modbus TCP or RTU (libmodbus), register map in docs/led-board-modbus.md.
//
// Before a take the table is written and read back in blocks (one read/write-multiple transaction per 121
// registers), then the board's own CRC is checked; only a verified table is armed. From Arm() until Disarm() the bus
// carries nothing but the status poll (and a blackout, should one come): every other transaction is refused here,
// before it reaches the bus. The status poll runs on a thread of its own, feeds the board's watchdog, and is what
// State() reports (State() itself never touches the bus). A board that stops answering is a fault, named with the
// board, the register and the cause, and kept in the take's faults.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/light/light_driver.h"
#include "stage/v1/rig.pb.h"

typedef struct _modbus modbus_t;  // libmodbus's context; its header stays in the .cc

namespace stage::light {

struct ModbusDriverOptions {
  // The light node (for messages) and its channel count, which the board must have.
  std::string node_id;
  uint32_t channel_count = 0;
  // Transport, unit id, timeout and retries, from the rig.
  v1::ModbusLightSettings settings;
  // Per channel, mA at full scale (written to the board's current limits); 0 where no emitter is wired.
  std::vector<uint16_t> current_limits_ma;
  // The status poll's period, ms. It is the only traffic while armed. Default 250 (4 Hz).
  int poll_interval_ms = 250;
  // The board's watchdog while armed, ms: quiet for this long (the node died, the link broke), it goes dark.
  // 0 = off. Default 1000 (four missed polls).
  int board_watchdog_ms = 1000;

  absl::Status Validate() const;
};

// Options for a modbus light node of the rig: settings, channel count, current limits from its units.
absl::StatusOr<ModbusDriverOptions> ModbusDriverOptionsFromRig(const v1::LightNodeConfig& config);

class ModbusLightDriver final : public LightDriver {
 public:
  // Connects, reads the board's identity and checks it (a FaStage board, this map's version, the node's channel
  // count). Unavailable names the board when it does not answer.
  static absl::StatusOr<std::unique_ptr<ModbusLightDriver>> Open(ModbusDriverOptions options);
  // Stops polling and disconnects; does not change the board's mode (LightNode blacks out first).
  ~ModbusLightDriver() override;

  DriverDescription Describe() const override;
  absl::Status LoadPatternTable(const PatternTable& table) override;
  absl::Status Arm() override;
  absl::Status Disarm() override;
  absl::Status Blackout() override;
  absl::Status ResetBlackout() override;
  DriverState State() const override;

  // Modbus transactions sent since Open (each retry counts), and those refused while armed.
  uint64_t transactions() const { return transactions_.load(); }
  uint64_t refused_while_armed() const { return refused_.load(); }
  // Reads the status block now (outside the poll's rhythm; refused while armed like any other transaction).
  absl::Status ReadStatusNow();

 private:
  enum class Purpose { kSetup, kStatusPoll, kArm, kDisarm, kBlackout };
  explicit ModbusLightDriver(ModbusDriverOptions options);
  absl::Status Connect();
  // Runs `call` (a libmodbus call returning < 0 on failure) with retries, under the bus lock, if the take window
  // allows `purpose`. Errors name the node, the board, `what` and `address`.
  absl::Status Transact(Purpose purpose, const std::string& what, uint16_t address, const std::function<int()>& call);
  // Status block -> cached state. Called with state_mutex_ held.
  void ApplyStatus(const uint16_t* regs);
  absl::Status PollStatus(Purpose purpose);
  void NoteBoardFault(const std::string& kind, const std::string& detail = "");
  void PollLoop();
  std::string Who() const;

  ModbusDriverOptions options_;
  std::string endpoint_;
  modbus_t* ctx_ = nullptr;  // guarded by bus_mutex_
  mutable std::mutex bus_mutex_;
  // Armed on the board: only the status poll, disarm and blackout may go out.
  std::atomic<bool> take_window_{false};
  std::atomic<uint64_t> transactions_{0};
  std::atomic<uint64_t> refused_{0};

  mutable std::mutex state_mutex_;
  DriverState state_;                  // guarded by state_mutex_
  std::string link_fault_;             // guarded by state_mutex_: the board is not answering, in words
  // Guarded by state_mutex_: the board's fault bits as the status last read them, each as (kind, what varies).
  std::vector<std::pair<std::string, std::string>> board_faults_;
  uint32_t max_rows_ = 0;
  std::string model_;
  uint16_t firmware_ = 0;

  std::mutex poll_mutex_;
  std::condition_variable poll_wake_;
  bool stopping_ = false;  // guarded by poll_mutex_
  std::thread poll_thread_;
};

}  // namespace stage::light
