// Modbus interoperability with code this project did not write: the light node's driver against a board served by
// Debian's python3-pymodbus (tests/support/pymodbus_led_board.py, the register map of docs/led-board-modbus.md), and
// the simulator's fake board (the fake-led-board program) answering mbpoll, over TCP and over RTU on a socat
// pseudo-terminal pair, and a pymodbus client.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <regex>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "modbus_light_driver.h"
#include "stage/common/subprocess.h"
#include "stage/light/led_board_map.h"
#include "test_support.h"

namespace stage::light {
namespace {

using ::testing::HasSubstr;
using namespace std::chrono_literals;
using testing::RunCommand;

constexpr char kPython[] = "/usr/bin/python3";  // Debian's, with python3-pymodbus

// Waits for a "ready <what>" line in `path`; returns <what>.
std::string WaitReady(const std::string& path, Subprocess& process) {
  for (int i = 0; i < 300; ++i) {
    std::ifstream in(path);
    std::string word, what;
    if (in >> word >> what && word == "ready") return what;
    if (process.Poll()) return "";
    std::this_thread::sleep_for(20ms);
  }
  return "";
}

PatternTable Table(uint32_t channels) {
  PatternTable t;
  for (uint32_t r = 0; r < 38; ++r) {
    t.row_names.push_back(absl::StrCat("p", r));
    ChannelLevels levels(channels);
    for (uint32_t c = 0; c < channels; ++c) levels[c] = static_cast<uint16_t>((r * 1013 + c * 7 + 3) % 65536);
    t.rows.push_back(levels);
  }
  return t;
}

TEST(ModbusInteropTest, TheDriverWorksAgainstAPymodbusBoard) {
  testing::TempDir dir;
  auto server = Subprocess::Spawn(
      {.argv = {kPython, std::string(FASTAGE_SOURCE_DIR) + "/tests/support/pymodbus_led_board.py", "--channels", "64"},
       .stdout_path = dir.path() + "/out",
       .stderr_path = dir.path() + "/err"});
  ASSERT_TRUE(server.ok()) << server.status();
  const std::string port = WaitReady(dir.path() + "/out", **server);
  ASSERT_FALSE(port.empty()) << testing::ReadFile(dir.path() + "/err");
  ModbusDriverOptions o;
  o.node_id = "lights-pymodbus";
  o.channel_count = 64;
  o.settings.mutable_tcp()->set_host("127.0.0.1");
  uint32_t p = 0;
  ASSERT_TRUE(absl::SimpleAtoi(port, &p));
  o.settings.mutable_tcp()->set_port(p);
  o.settings.set_unit_id(1);
  o.settings.set_timeout_ms(500);
  o.settings.set_retries(1);
  o.current_limits_ma.assign(64, 700);
  o.poll_interval_ms = 100;
  o.board_watchdog_ms = 0;
  {
    auto driver = ModbusLightDriver::Open(o);
    ASSERT_TRUE(driver.ok()) << driver.status();
    // Upload and verify through pymodbus's read/write-multiple (0x17), arm, blackout, reset.
    ASSERT_TRUE((*driver)->LoadPatternTable(Table(64)).ok());
    ASSERT_TRUE((*driver)->Arm().ok());
    EXPECT_EQ((*driver)->State().mode, DriverMode::kArmed);
    ASSERT_TRUE((*driver)->Blackout().ok());
    std::this_thread::sleep_for(250ms);
    EXPECT_EQ((*driver)->State().mode, DriverMode::kBlackout);
    ASSERT_TRUE((*driver)->ResetBlackout().ok());
    EXPECT_EQ((*driver)->State().mode, DriverMode::kIdle);
    // pymodbus's exceptions reach the caller by name: a board refuses to leave idle for armed without a valid
    // table; here, the driver refuses a 65-row table before the bus.
    PatternTable big = Table(64);
    big.rows.resize(65, big.rows[0]);
    EXPECT_THAT(std::string((*driver)->LoadPatternTable(big).message()), HasSubstr("the board holds at most 64"));
  }
  (*server)->Terminate(2s);
}

// The fake board as a program, serving on `transport` ("--tcp", "127.0.0.1:0" or "--rtu", path).
struct FakeBoardProcess {
  std::unique_ptr<Subprocess> process;
  std::string endpoint;
};
FakeBoardProcess StartFakeBoard(const testing::TempDir& dir, std::vector<std::string> args) {
  std::vector<std::string> argv = {testing::BinDir() + "/fake-led-board", "--channels", "64"};
  argv.insert(argv.end(), args.begin(), args.end());
  auto p = Subprocess::Spawn({.argv = argv, .stdout_path = dir.path() + "/board.out",
                              .stderr_path = dir.path() + "/board.err"});
  EXPECT_TRUE(p.ok()) << p.status();
  if (!p.ok()) return {};
  FakeBoardProcess f{std::move(*p), ""};
  f.endpoint = WaitReady(dir.path() + "/board.out", *f.process);
  EXPECT_FALSE(f.endpoint.empty()) << testing::ReadFile(dir.path() + "/board.err");
  return f;
}

// mbpoll's "[ref]: \tvalue" lines, by reference.
std::map<int, std::string> MbpollValues(const std::string& out) {
  std::map<int, std::string> values;
  static const std::regex line(R"(\[(\d+)\]:\s+(\S+))");
  for (std::sregex_iterator it(out.begin(), out.end(), line), end; it != end; ++it) {
    values[std::stoi((*it)[1])] = (*it)[2];
  }
  return values;
}

TEST(ModbusInteropTest, MbpollReadsAndWritesTheFakeBoardOverTcp) {
  testing::TempDir dir;
  FakeBoardProcess board = StartFakeBoard(dir, {"--tcp", "127.0.0.1:0"});
  ASSERT_THAT(board.endpoint, HasSubstr("tcp://127.0.0.1:"));
  const std::string port = board.endpoint.substr(board.endpoint.rfind(':') + 1);
  // Identity, 0-based references, hex.
  auto id = RunCommand({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "0", "-c", "5", "-t",
                        "4:hex", "-1", "127.0.0.1"},
                       10s);
  ASSERT_TRUE(id.exit.ok()) << id.out << id.err;
  auto v = MbpollValues(id.out);
  EXPECT_EQ(v[0], "0x4653");  // magic
  EXPECT_EQ(v[1], "0x0001");  // map version
  EXPECT_EQ(v[3], "0x0040");  // 64 channels
  EXPECT_EQ(v[4], "0x0040");  // 64 rows
  // Write three table entries, read them back.
  auto write = RunCommand({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "4096", "-t", "4",
                           "127.0.0.1", "1000", "2000", "65535"},
                          10s);
  ASSERT_TRUE(write.exit.ok()) << write.out << write.err;
  auto read = RunCommand({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "4096", "-c", "3", "-t",
                          "4", "-1", "127.0.0.1"},
                         10s);
  ASSERT_TRUE(read.exit.ok()) << read.out << read.err;
  v = MbpollValues(read.out);
  EXPECT_EQ(v[4096], "1000");
  EXPECT_EQ(v[4097], "2000");
  EXPECT_EQ(v[4098], "65535");
  // The board's exceptions reach a standard client: mode 7 is an illegal data value.
  auto bad = RunCommand({"/usr/bin/mbpoll", "-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "256", "-t", "4",
                         "127.0.0.1", "7"},
                        10s);
  EXPECT_FALSE(bad.exit.ok());
  EXPECT_THAT(bad.out + bad.err, HasSubstr("Illegal data value"));
  board.process->Terminate(2s);
}

TEST(ModbusInteropTest, MbpollReadsTheFakeBoardOverRtu) {
  testing::TempDir dir;
  testing::PseudoTerminalPair pty(dir);
  ASSERT_TRUE(pty.ok()) << pty.error();
  FakeBoardProcess board = StartFakeBoard(dir, {"--rtu", pty.board(), "--unit", "5", "--parity", "E"});
  ASSERT_EQ(board.endpoint, "rtu:" + pty.board());
  auto id = RunCommand({"/usr/bin/mbpoll", "-m", "rtu", "-b", "115200", "-P", "even", "-a", "5", "-0", "-r", "272",
                        "-c", "8", "-t", "4:hex", "-1", pty.host()},
                       10s);
  ASSERT_TRUE(id.exit.ok()) << id.out << id.err;
  auto v = MbpollValues(id.out);
  EXPECT_EQ(v[272], "0x0000");  // status: idle, no table
  EXPECT_EQ(v[274], "0xFFFF");  // current step: dark
  EXPECT_EQ(v[277], "0x013B");  // 31.5 degC
  EXPECT_EQ(v[279], "0x02BC");  // limit 70.0 degC
  board.process->Terminate(2s);
}

TEST(ModbusInteropTest, APymodbusClientUsesTheFakeBoard) {
  testing::TempDir dir;
  FakeBoardProcess board = StartFakeBoard(dir, {"--tcp", "127.0.0.1:0"});
  const std::string port = board.endpoint.substr(board.endpoint.rfind(':') + 1);
  // Two rows of 64 channels through pymodbus's client: write them, set the sequence length and CRC-16/MODBUS, arm.
  const std::string script = dir.Write("client.py", R"(
import sys
from pymodbus.client import ModbusTcpClient
c = ModbusTcpClient("127.0.0.1", port=int(sys.argv[1]))
assert c.connect()
rows = [[(r * 100 + ch) for ch in range(64)] for r in range(2)]
flat = rows[0] + rows[1]
# pymodbus 3.0's readwrite_registers takes unit=, not slave= (which it ignores, sending unit 0)
r = c.readwrite_registers(read_address=0x1000, read_count=64, write_address=0x1000, write_registers=flat[:64], unit=1)
assert not r.isError() and r.registers == flat[:64], r
assert not c.write_registers(0x1040, flat[64:], slave=1).isError()
crc = 0xFFFF
for v in flat:
    for byte in (v >> 8, v & 0xFF):
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
assert not c.write_registers(0x0101, [2, crc], slave=1).isError()
assert not c.write_register(0x0100, 1, slave=1).isError()
s = c.read_holding_registers(0x0110, 8, slave=1)
print("status", s.registers[0], "crc", s.registers[6], "expected", crc)
bad = c.write_register(0x0100, 9, slave=1)
print("exception", bad.exception_code if bad.isError() else "none")
)");
  auto r = RunCommand({kPython, script, port}, 20s);
  ASSERT_TRUE(r.exit.ok()) << r.out << r.err;
  // Table valid and armed; the board's CRC is the client's; a bad mode is exception 3.
  EXPECT_THAT(r.out, HasSubstr(absl::StrCat("status ", board::kStatusTableValid | board::kStatusArmed, " crc ")));
  std::smatch m;
  ASSERT_TRUE(std::regex_search(r.out, m, std::regex(R"(crc (\d+) expected (\d+))"))) << r.out;
  EXPECT_EQ(m[1], m[2]);
  EXPECT_THAT(r.out, HasSubstr("exception 3"));
  board.process->Terminate(2s);
}

// A board powered after its light node. The light-node program, with the shipped rig's lights-modbus-1 on a loopback
// port where nothing answers yet: without --device-wait-s it exits at once naming the board; with it, it says it is
// trying again, and serves once a fake board comes up on that port.
TEST(ModbusInteropTest, ALightNodeWaitsForItsBoardWhenToldTo) {
  testing::TempDir dir;
  int port = 0;
  {
    // A free port: bound, read, closed (nothing else on loopback takes it in the next moments).
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof(a)), 0);
    socklen_t len = sizeof(a);
    ASSERT_EQ(getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len), 0);
    port = ntohs(a.sin_port);
    close(fd);
  }
  std::string rig = testing::ReadFile(std::string(FASTAGE_SOURCE_DIR) + "/common/rigs/fastage.yaml");
  const std::string board = "host: led-board-1.stage.lan, port: 502";
  ASSERT_NE(rig.find(board), std::string::npos);
  rig.replace(rig.find(board), board.size(), absl::StrCat("host: 127.0.0.1, port: ", port));
  const std::string rig_path = dir.path() + "/rig.yaml";
  std::ofstream(rig_path) << rig;
  const std::vector<std::string> node = {testing::BinDir() + "/light-node", "--config", rig_path, "--id",
                                         "lights-modbus-1", "--port-file", dir.path() + "/node.port"};

  testing::CommandResult at_once = RunCommand(node, 30s);
  EXPECT_EQ(at_once.exit.exit_code, 1);
  EXPECT_THAT(at_once.err, HasSubstr(absl::StrCat("board tcp://127.0.0.1:", port)));

  std::vector<std::string> waiting = node;
  waiting.insert(waiting.end(), {"--device-wait-s", "60"});
  auto p = Subprocess::Spawn({.argv = waiting, .stderr_path = dir.path() + "/node.err"});
  ASSERT_TRUE(p.ok()) << p.status();
  for (int i = 0; i < 200 && testing::ReadFile(dir.path() + "/node.err").find("trying again") == std::string::npos;
       ++i) {
    std::this_thread::sleep_for(50ms);
  }
  EXPECT_THAT(testing::ReadFile(dir.path() + "/node.err"), HasSubstr("trying again every second"));
  EXPECT_FALSE((*p)->Poll()) << "still waiting, not exited";
  FakeBoardProcess fake = StartFakeBoard(dir, {"--tcp", absl::StrCat("127.0.0.1:", port)});
  ASSERT_FALSE(fake.endpoint.empty());
  bool serving = false;
  for (int i = 0; i < 200 && !serving; ++i) {
    serving = testing::ReadFile(dir.path() + "/node.err").find("serving on") != std::string::npos;
    if (!serving) std::this_thread::sleep_for(50ms);
  }
  EXPECT_TRUE(serving) << testing::ReadFile(dir.path() + "/node.err");
  EXPECT_FALSE((*p)->Poll());
  (*p)->Terminate(5s);
  fake.process->Terminate(2s);
}

}  // namespace
}  // namespace stage::light
