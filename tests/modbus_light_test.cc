// The light node's Modbus driver against the simulator's fake LED board (a libmodbus server for
// docs/led-board-modbus.md): over loopback TCP and over RTU on a pseudo-terminal pair made by socat. Upload, read
// back, arm, step through a take, blackout; a corrupted entry refuses to arm; a board that stops answering is a
// fault of the take; nothing but the status poll goes on the bus while armed; the board's own watchdog.
#include <chrono>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "modbus_light_driver.h"
#include "stage/common/subprocess.h"
#include "stage/light/led_board_map.h"
#include "stage/sim/fake_led_board.h"
#include "test_support.h"

namespace stage::light {
namespace {

using ::testing::HasSubstr;
using namespace std::chrono_literals;

// A 38-row table whose every entry differs (so a misplaced block shows), within 16 bits.
PatternTable Table(uint32_t channels, uint32_t rows = 38) {
  PatternTable t;
  t.pattern_set = "test";
  for (uint32_t r = 0; r < rows; ++r) {
    t.row_names.push_back(absl::StrCat("p", r));
    ChannelLevels levels(channels);
    for (uint32_t c = 0; c < channels; ++c) levels[c] = static_cast<uint16_t>((r * 997 + c * 31 + 1) % 60000);
    t.rows.push_back(levels);
  }
  return t;
}

ModbusDriverOptions TcpOptions(const sim::FakeLedBoard& board, uint32_t channels) {
  ModbusDriverOptions o;
  o.node_id = "lights-test";
  o.channel_count = channels;
  o.settings.mutable_tcp()->set_host("127.0.0.1");
  o.settings.mutable_tcp()->set_port(static_cast<uint32_t>(board.port()));
  o.settings.set_unit_id(1);
  o.settings.set_timeout_ms(100);
  o.settings.set_retries(2);
  o.current_limits_ma.assign(channels, 700);
  o.poll_interval_ms = 100;
  o.board_watchdog_ms = 400;
  return o;
}

std::unique_ptr<sim::FakeLedBoard> TcpBoard(uint32_t channels) {
  sim::FakeLedBoardOptions o;
  o.board_id = "board-test";
  o.channel_count = channels;
  o.tcp_host = "127.0.0.1";
  auto board = sim::FakeLedBoard::Start(o);
  EXPECT_TRUE(board.ok()) << board.status();
  return board.ok() ? std::move(*board) : nullptr;
}

// A driver on `board` (64 channels) with the test table loaded and armed.
void OpenArmed(sim::FakeLedBoard& board, std::unique_ptr<ModbusLightDriver>* driver) {
  auto opened = ModbusLightDriver::Open(TcpOptions(board, 64));
  ASSERT_TRUE(opened.ok()) << opened.status();
  ASSERT_TRUE((*opened)->LoadPatternTable(Table(64)).ok());
  ASSERT_TRUE((*opened)->Arm().ok());
  *driver = std::move(*opened);
}

// Upload, verify, arm, step, blackout: the whole take as a light node drives it.
void RunTake(sim::FakeLedBoard& board, ModbusLightDriver& driver, uint32_t channels) {
  const PatternTable table = Table(channels);
  const uint64_t before = driver.transactions();
  ASSERT_TRUE(driver.LoadPatternTable(table).ok());
  // 38 x channels registers in blocks of 121 (each written and read back at once), the limits, the commit.
  const uint64_t blocks = (38 * channels + 120) / 121;
  EXPECT_GE(driver.transactions() - before, blocks + 2);
  EXPECT_LE(driver.transactions() - before, blocks + 2 + 2);  // + at most two status polls in between
  ASSERT_TRUE(driver.Arm().ok());
  EXPECT_EQ(driver.State().mode, DriverMode::kArmed);
  // Nothing lit before the first slot-clock edge; then row k on edge k + 1, wrapping after 38.
  EXPECT_EQ(board.leds().Outputs(), ChannelLevels(channels, 0));
  for (int edge = 1; edge <= 40; ++edge) {
    board.leds().Step();
    ASSERT_EQ(board.leds().Outputs(), table.rows[static_cast<size_t>((edge - 1) % 38)]) << "edge " << edge;
  }
  std::this_thread::sleep_for(300ms);  // the poll thread reads the board's state
  const DriverState armed = driver.State();
  EXPECT_EQ(armed.steps, 40u);
  EXPECT_EQ(armed.current_row, 1);
  ASSERT_TRUE(armed.temperature_c.has_value());
  EXPECT_NEAR(*armed.temperature_c, 31.5, 0.05);
  EXPECT_TRUE(armed.take_faults.empty());
  // Blackout: dark at once, latched: steps change nothing, arming is refused until reset.
  ASSERT_TRUE(driver.Blackout().ok());
  EXPECT_EQ(board.leds().Outputs(), ChannelLevels(channels, 0));
  board.leds().Step();
  EXPECT_EQ(board.leds().Outputs(), ChannelLevels(channels, 0));
  EXPECT_EQ(driver.State().mode, DriverMode::kBlackout);
  EXPECT_FALSE(driver.Arm().ok());
  ASSERT_TRUE(driver.ResetBlackout().ok());
  EXPECT_EQ(driver.State().mode, DriverMode::kIdle);
}

TEST(ModbusLightTest, UploadVerifyArmStepAndBlackoutOverTcp) {
  auto board = TcpBoard(64);
  ASSERT_NE(board, nullptr);
  auto driver = ModbusLightDriver::Open(TcpOptions(*board, 64));
  ASSERT_TRUE(driver.ok()) << driver.status();
  EXPECT_EQ((*driver)->Describe().backend, "modbus");
  EXPECT_THAT((*driver)->Describe().device, HasSubstr(absl::StrCat("tcp://127.0.0.1:", board->port(), " unit 1")));
  RunTake(*board, **driver, 64);
}

TEST(ModbusLightTest, UploadVerifyArmStepAndBlackoutOverRtuOnAPseudoTerminal) {
  testing::TempDir dir;
  testing::PseudoTerminalPair pty(dir);
  ASSERT_TRUE(pty.ok()) << pty.error();
  sim::FakeLedBoardOptions bo;
  bo.board_id = "board-rtu";
  bo.channel_count = 16;
  bo.unit_id = 7;
  bo.rtu_device = pty.board();
  auto board = sim::FakeLedBoard::Start(bo);
  ASSERT_TRUE(board.ok()) << board.status();
  ModbusDriverOptions o;
  o.node_id = "lights-rtu";
  o.channel_count = 16;
  o.settings.mutable_rtu()->set_device(pty.host());
  o.settings.mutable_rtu()->set_baud(115200);
  o.settings.mutable_rtu()->set_parity("N");
  o.settings.mutable_rtu()->set_data_bits(8);
  o.settings.mutable_rtu()->set_stop_bits(1);
  o.settings.set_unit_id(7);
  o.settings.set_timeout_ms(200);
  o.settings.set_retries(2);
  o.current_limits_ma.assign(16, 350);
  o.poll_interval_ms = 100;
  o.board_watchdog_ms = 0;
  auto driver = ModbusLightDriver::Open(o);
  ASSERT_TRUE(driver.ok()) << driver.status();
  EXPECT_THAT((*driver)->Describe().device, HasSubstr("rtu:" + pty.host() + "@115200 unit 7"));
  RunTake(**board, **driver, 16);
}

TEST(ModbusLightTest, ACorruptedEntryRefusesToArmNamingBoardAndEntry) {
  auto board = TcpBoard(64);
  ASSERT_NE(board, nullptr);
  board->SetCorruptEntry(5, 7);
  auto driver = ModbusLightDriver::Open(TcpOptions(*board, 64));
  ASSERT_TRUE(driver.ok()) << driver.status();
  const PatternTable table = Table(64);
  const absl::Status s = (*driver)->LoadPatternTable(table);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss);
  const uint16_t address = board::TableAddress(5, 7, 64);
  EXPECT_THAT(std::string(s.message()),
              HasSubstr(absl::StrCat("light node \"lights-test\" (board tcp://127.0.0.1:", board->port(), " unit 1)")));
  EXPECT_THAT(std::string(s.message()),
              HasSubstr(absl::StrFormat("row 5 (p5) channel 7 (register 0x%04X): wrote %d, the board holds %d", address,
                                        table.rows[5][7], table.rows[5][7] ^ 0x0100)));
  // The board will not arm on that table either (its CRC differs), and nothing lights.
  EXPECT_FALSE((*driver)->Arm().ok());
  board->leds().Step();
  EXPECT_EQ(board->leds().Outputs(), ChannelLevels(64, 0));
}

TEST(ModbusLightTest, OnlyTheStatusPollGoesOnTheBusWhileArmed) {
  auto board = TcpBoard(64);
  ASSERT_NE(board, nullptr);
  std::unique_ptr<ModbusLightDriver> driver;
  ASSERT_NO_FATAL_FAILURE(OpenArmed(*board, &driver));
  board->ClearRequests();
  // A take of 1.2 s on a 912 Hz slot clock, with the node asked to do other things meanwhile.
  std::atomic<bool> stop{false};
  std::thread clock([&] {
    auto next = std::chrono::steady_clock::now();
    while (!stop.load()) {
      next += std::chrono::microseconds(1096);
      std::this_thread::sleep_until(next);
      board->leds().Step();
    }
  });
  const auto start = std::chrono::steady_clock::now();
  std::this_thread::sleep_for(300ms);
  const absl::Status reload = driver->LoadPatternTable(Table(64));
  const absl::Status read = driver->ReadStatusNow();
  std::this_thread::sleep_for(900ms);
  const auto requests = board->Requests();
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  stop.store(true);
  clock.join();
  EXPECT_EQ(reload.code(), absl::StatusCode::kFailedPrecondition) << reload;  // not idle
  EXPECT_EQ(read.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(read.message()), HasSubstr("only the status poll, disarm and blackout go on the bus"));
  EXPECT_EQ(driver->refused_while_armed(), 1u);
  // The poll every 100 ms, nothing else: reads of the status block only.
  ASSERT_FALSE(requests.empty());
  for (const sim::BoardRequest& r : requests) {
    EXPECT_EQ(r.function, 0x03);
    EXPECT_EQ(r.address, board::kStatus);
    EXPECT_EQ(r.count, board::kStatusRegisters);
  }
  EXPECT_LE(requests.size(), static_cast<size_t>(seconds / 0.1) + 1);
  EXPECT_GE(requests.size(), static_cast<size_t>(seconds / 0.1) - 3);
  ASSERT_TRUE(driver->Disarm().ok());
}

TEST(ModbusLightTest, ABoardThatStopsAnsweringIsAFaultOfTheTake) {
  auto board = TcpBoard(64);
  ASSERT_NE(board, nullptr);
  std::unique_ptr<ModbusLightDriver> driver;
  ASSERT_NO_FATAL_FAILURE(OpenArmed(*board, &driver));
  board->SetNoAnswer(true);
  // A poll's three tries time out after 3 x 100 ms.
  DriverState s;
  for (int i = 0; i < 40; ++i) {
    std::this_thread::sleep_for(50ms);
    s = driver->State();
    if (!s.take_faults.empty()) break;
  }
  ASSERT_EQ(s.take_faults.size(), 1u);
  EXPECT_THAT(s.take_faults[0], HasSubstr("board not answering"));
  ASSERT_FALSE(s.faults.empty());
  EXPECT_THAT(s.faults.back(), HasSubstr(absl::StrCat("light node \"lights-test\" (board tcp://127.0.0.1:",
                                                      board->port(), " unit 1): status poll (register 0x0110): ")));
  EXPECT_THAT(s.faults.back(), HasSubstr("3 tries; the board is not answering"));
  const absl::Status disarm = driver->Disarm();
  EXPECT_EQ(disarm.code(), absl::StatusCode::kUnavailable);
  // It answers again: the current fault clears, the take's record keeps it until the next arm.
  board->SetNoAnswer(false);
  std::this_thread::sleep_for(800ms);
  s = driver->State();
  EXPECT_TRUE(s.faults.empty()) << s.faults.front();
  EXPECT_EQ(s.take_faults.size(), 1u);
}

TEST(ModbusLightTest, OverTemperatureBlacksOutAndHoldsTheBlackout) {
  auto board = TcpBoard(64);
  ASSERT_NE(board, nullptr);
  std::unique_ptr<ModbusLightDriver> driver;
  ASSERT_NO_FATAL_FAILURE(OpenArmed(*board, &driver));
  board->leds().Step();
  board->SetOverTemperature(true);
  EXPECT_EQ(board->leds().Outputs(), ChannelLevels(64, 0));
  std::this_thread::sleep_for(300ms);
  DriverState s = driver->State();
  EXPECT_EQ(s.mode, DriverMode::kBlackout);
  ASSERT_EQ(s.faults.size(), 1u);
  EXPECT_EQ(s.faults[0], "board: over temperature (74.5 degC, limit 70.0 degC)");
  ASSERT_EQ(s.take_faults.size(), 1u);
  const absl::Status reset = driver->ResetBlackout();
  EXPECT_EQ(reset.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(reset.message()), HasSubstr("leaving blackout (register 0x0100): the board answered"));
  board->SetOverTemperature(false);
  EXPECT_TRUE(driver->ResetBlackout().ok());
  EXPECT_EQ(driver->State().mode, DriverMode::kIdle);
}

TEST(ModbusLightTest, TheBoardGoesDarkWhenItsHostGoesQuietWhileArmed) {
  auto board = TcpBoard(64);
  ASSERT_NE(board, nullptr);
  {
    std::unique_ptr<ModbusLightDriver> driver;  // watchdog 400 ms, poll 100 ms
    ASSERT_NO_FATAL_FAILURE(OpenArmed(*board, &driver));
    board->leds().Step();
    std::this_thread::sleep_for(600ms);  // polled: still armed and lit
    EXPECT_EQ(board->leds().State().mode, DriverMode::kArmed);
  }  // the host dies without a word (no blackout from it)
  std::this_thread::sleep_for(700ms);
  EXPECT_EQ(board->leds().State().mode, DriverMode::kBlackout);
  EXPECT_EQ(board->leds().Outputs(), ChannelLevels(64, 0));
}

TEST(ModbusLightTest, ABoardThatDoesNotFitTheRigIsRefusedByName) {
  auto board = TcpBoard(32);
  ASSERT_NE(board, nullptr);
  auto driver = ModbusLightDriver::Open(TcpOptions(*board, 64));
  ASSERT_FALSE(driver.ok());
  EXPECT_THAT(std::string(driver.status().message()),
              HasSubstr("the board has 32 channels, the rig says channel_count 64"));
  ModbusDriverOptions nowhere = TcpOptions(*board, 64);
  board.reset();  // its port is closed now
  auto gone = ModbusLightDriver::Open(nowhere);
  ASSERT_FALSE(gone.ok());
  EXPECT_EQ(gone.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(std::string(gone.status().message()), HasSubstr("reading the board's identity (register 0x0000)"));
}

}  // namespace
}  // namespace stage::light
