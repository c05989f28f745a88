// fake-led-board: a simulated LED driver board on a real Modbus link (docs/led-board-modbus.md), for trying Modbus
// tools and light nodes without hardware. Serves until SIGINT or SIGTERM.
#include <chrono>
#include <cstdio>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/shutdown.h"
#include "stage/sim/fake_led_board.h"

int main(int argc, char** argv) {
  stage::BlockShutdownSignals();
  CLI::App app{
      "A simulated FaStage LED driver board: a Modbus TCP or RTU server implementing docs/led-board-modbus.md. Prints "
      "\"ready <endpoint>\" on stdout once it serves.",
      "fake-led-board"};
  stage::sim::FakeLedBoardOptions o;
  std::string tcp, log_level = "warn", corrupt;
  double step_hz = 0;
  bool no_answer = false, over_temperature = false;
  auto* transport = app.add_option_group("transport", "where the board listens (one of)");
  transport->add_option("--tcp", tcp, "host:port to listen on (port 0 picks a free one)");
  transport->add_option("--rtu", o.rtu_device, "serial device to serve on (e.g. one end of a socat pty pair)");
  transport->require_option(1);
  app.add_option("--baud", o.rtu_baud, "RTU baud rate")->capture_default_str();
  app.add_option("--parity", o.rtu_parity, "RTU parity: N, E or O")->capture_default_str();
  app.add_option("--unit", o.unit_id, "Modbus unit (slave) id the board answers on RTU")->capture_default_str();
  app.add_option("--channels", o.channel_count, "LED channels (1..64)")->capture_default_str();
  app.add_option("--max-rows", o.max_rows, "pattern table capacity, rows (1..64)")->capture_default_str();
  app.add_option("--id", o.board_id, "name in the log")->capture_default_str();
  app.add_option("--step-hz", step_hz, "step the LEDs on an internal slot clock at this rate (0: never)")
      ->capture_default_str();
  app.add_flag("--no-answer", no_answer, "fault: read requests and never answer");
  app.add_option("--corrupt", corrupt, "fault: ROW,CHANNEL of a table entry that keeps a flipped bit");
  app.add_flag("--over-temperature", over_temperature, "fault: over temperature from the start (blackout)");
  app.add_option("--log-level", log_level, "trace, debug, info, warn, error")->capture_default_str();
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  const char* kProgram = "fake-led-board";
  if (auto s = stage::InitLogging(kProgram, log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (!tcp.empty()) {
    std::vector<std::string> parts = absl::StrSplit(tcp, absl::MaxSplits(':', 1));
    if (parts.size() != 2 || !absl::SimpleAtoi(parts[1], &o.tcp_port)) {
      return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--tcp wants host:port, got \"" + tcp + "\""));
    }
    o.tcp_host = parts[0];
  }
  auto board = stage::sim::FakeLedBoard::Start(o);
  if (!board.ok()) return stage::ReportFatal(kProgram, board.status());
  if (!corrupt.empty()) {
    std::vector<std::string> rc = absl::StrSplit(corrupt, ',');
    int row = 0, ch = 0;
    if (rc.size() != 2 || !absl::SimpleAtoi(rc[0], &row) || !absl::SimpleAtoi(rc[1], &ch)) {
      return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--corrupt wants ROW,CHANNEL"));
    }
    (*board)->SetCorruptEntry(row, ch);
  }
  (*board)->SetNoAnswer(no_answer);
  if (over_temperature) (*board)->SetOverTemperature(true);
  std::printf("ready %s\n", (*board)->endpoint().c_str());
  std::fflush(stdout);
  if (step_hz > 0) {
    const auto period = std::chrono::duration<double>(1.0 / step_hz);
    auto next = std::chrono::steady_clock::now();
    while (!stage::WaitForShutdownSignal(std::chrono::milliseconds(0))) {
      next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period);
      std::this_thread::sleep_until(next);
      (*board)->leds().Step();
    }
  } else {
    stage::WaitForShutdownSignal();
  }
  return 0;
}
