// The gpiod light backend on real GPIO character devices (label hw). Two ways, each skipping with its reason where
// this machine lacks it:
//  - the kernel's gpio-sim (configfs /sys/kernel/config/gpio-sim, root): the test makes a simulated chip, drives the
//    slot clock input through the line's pull, reads the channel outputs back through sysfs, and checks the kernel's
//    edge timestamps;
//  - a real chip named by FASTAGE_GPIO_CHIP, with FASTAGE_GPIO_LINES ("4,5,6:7": channel outputs, then the slot clock
//    line, all free to drive): the node generates the slot clock there and steps on it.
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gpiod_light_driver.h"
#include "gtest/gtest.h"
#include "stage/timing/slot_clock.h"

namespace stage::light {
namespace {

namespace fs = std::filesystem;

constexpr char kGpioSim[] = "/sys/kernel/config/gpio-sim";

int64_t NowNs() { return timing::HostClockNs(/*realtime_clock=*/false); }

bool WriteFile(const fs::path& path, const std::string& text) {
  std::ofstream out(path);
  out << text;
  out.flush();
  return static_cast<bool>(out);
}

std::string ReadFile(const fs::path& path) {
  std::ifstream in(path);
  std::string s;
  std::getline(in, s);
  return s;
}

// A gpio-sim chip with one bank of `lines` lines, made through configfs and removed again.
class GpioSimChip {
 public:
  static std::string WhyNot() {
    if (!fs::is_directory(kGpioSim)) {
      return absl::StrCat("no gpio-sim: ", kGpioSim,
                          " is absent (needs configfs mounted and the gpio-sim module: modprobe gpio-sim)");
    }
    if (access(kGpioSim, W_OK) != 0)
      return absl::StrCat("gpio-sim is present but ", kGpioSim, " is not writable (root)");
    return "";
  }

  explicit GpioSimChip(int lines) : dir_(fs::path(kGpioSim) / absl::StrCat("fastage-", getpid())) {
    std::error_code ec;
    fs::create_directory(dir_, ec);
    fs::create_directory(dir_ / "bank0", ec);
    ok_ = !ec && WriteFile(dir_ / "bank0" / "num_lines", std::to_string(lines)) && WriteFile(dir_ / "live", "1");
    if (ok_) {
      chip_ = ReadFile(dir_ / "bank0" / "chip_name");
      device_ = ReadFile(dir_ / "dev_name");
    }
  }
  ~GpioSimChip() {
    WriteFile(dir_ / "live", "0");
    std::error_code ec;
    fs::remove(dir_ / "bank0", ec);
    fs::remove(dir_, ec);
  }
  bool ok() const { return ok_ && !chip_.empty(); }
  const std::string& chip() const { return chip_; }
  fs::path Line(int offset) const {
    return fs::path("/sys/devices/platform") / device_ / chip_ / absl::StrCat("sim_gpio", offset);
  }
  // What the consumer drives on an output line.
  int Value(int offset) const { return std::atoi(ReadFile(Line(offset) / "value").c_str()); }
  // The simulated outside world pulls an input line: this makes its edges.
  bool Pull(int offset, bool up) const { return WriteFile(Line(offset) / "pull", up ? "pull-up" : "pull-down"); }

 private:
  fs::path dir_;
  bool ok_ = false;
  std::string chip_, device_;
};

// The three rows the gpio-sim tests step through, on three one-line channels.
const PatternTable& Rows() {
  static const PatternTable table{"t", {"a", "b", "c"}, {{65535, 0, 0}, {0, 65535, 0}, {65535, 65535, 65535}}};
  return table;
}

// The real lines of a gpio-sim chip, read back through sysfs right after every write, in the writing thread: what the
// kernel holds at each of the driver's edges, whatever the load (a sampler of its own would miss pulses on a busy
// machine).
class ReadBackLines final : public GpioLines {
 public:
  ReadBackLines(std::unique_ptr<GpioLines> real, const GpioSimChip& sim, std::vector<int> outputs, int clock)
      : real_(std::move(real)), sim_(sim), outputs_(std::move(outputs)), clock_(clock) {}
  std::string Describe() const override { return real_->Describe(); }
  absl::Status SetOutputs(const std::vector<uint8_t>& values) override {
    absl::Status s = real_->SetOutputs(values);
    if (s.ok()) {
      for (size_t i = 0; i < values.size(); ++i) mismatches += sim_.Value(outputs_[i]) != values[i] ? 1 : 0;
    }
    return s;
  }
  absl::StatusOr<std::vector<int64_t>> WaitEdges(std::chrono::nanoseconds timeout) override {
    return real_->WaitEdges(timeout);
  }
  absl::Status SetClock(bool high) override {
    absl::Status s = real_->SetClock(high);
    if (s.ok() && high) {
      ++rises_written;
      rises_held += sim_.Value(clock_) == 1 ? 1 : 0;
    }
    return s;
  }
  std::atomic<int> rises_written{0}, rises_held{0}, mismatches{0};

 private:
  std::unique_ptr<GpioLines> real_;
  const GpioSimChip& sim_;
  std::vector<int> outputs_;
  int clock_;
};

// A driver on a gpio-sim chip: channels on lines 0-2, the slot clock on line 7 (its output when `drives`, else an input
// the test pulls, first low), at `rate_hz`; Rows() loaded, armed. With `read_back`, its lines are read back after every
// write (ReadBackLines, left there).
std::unique_ptr<GpiodLightDriver> ArmedOnSim(const GpioSimChip& sim, const std::string& id, double rate_hz,
                                             bool drives, ReadBackLines** read_back = nullptr) {
  GpiodDriverOptions o;
  o.node_id = id;
  o.channel_count = 3;
  o.lines.chip = sim.chip();
  o.lines.outputs = {0, 1, 2};
  o.lines.slot_clock_line = 7;
  o.lines.drives_slot_clock = drives;
  o.slot_rate_hz = rate_hz;
  absl::StatusOr<std::unique_ptr<GpiodLightDriver>> driver;
  if (read_back == nullptr) {
    driver = GpiodLightDriver::Open(o);
  } else {
    auto lines = OpenGpiodLines(o.lines);
    EXPECT_TRUE(lines.ok()) << lines.status();
    if (!lines.ok()) return nullptr;
    auto wrapped = std::make_unique<ReadBackLines>(*std::move(lines), sim, std::vector<int>{0, 1, 2}, 7);
    *read_back = wrapped.get();
    driver = GpiodLightDriver::Create(o, std::move(wrapped));
  }
  EXPECT_TRUE(driver.ok()) << driver.status();
  if (!driver.ok()) return nullptr;
  if (!drives) {
    EXPECT_TRUE(sim.Pull(7, false));
  }
  EXPECT_TRUE((*driver)->LoadPatternTable(Rows()).ok());
  EXPECT_TRUE((*driver)->Arm().ok());
  return *std::move(driver);
}

TEST(GpiodLightTest, StepsOnKernelTimestampedEdgesOfGpioSim) {
  if (std::string why = GpioSimChip::WhyNot(); !why.empty()) GTEST_SKIP() << why;
  GpioSimChip sim(8);
  ASSERT_TRUE(sim.ok()) << "could not make a gpio-sim chip";
  // The pulls below come every few ms (more on a busy machine): a 1 Hz clock, so that no gap between them reads as
  // edges lost (1.5 periods).
  auto driver = ArmedOnSim(sim, "lights-gpio-sim", 1, /*drives=*/false);
  ASSERT_NE(driver, nullptr);
  const PatternTable& table = Rows();
  const int64_t start = NowNs();
  for (int edge = 0; edge < 6; ++edge) {
    ASSERT_TRUE(sim.Pull(7, true));
    for (int i = 0; i < 500 && driver->State().steps < static_cast<uint64_t>(edge + 1); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    ASSERT_EQ(driver->State().steps, static_cast<uint64_t>(edge + 1)) << "edge " << edge;
    const ChannelLevels& row = table.rows[static_cast<size_t>(edge % 3)];
    for (int c = 0; c < 3; ++c) EXPECT_EQ(sim.Value(c), row[static_cast<size_t>(c)] ? 1 : 0) << "edge " << edge;
    ASSERT_TRUE(sim.Pull(7, false));  // falling edges do not step
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  MeasuredEdges m = driver->Edges();
  ASSERT_EQ(m.times_ns.size(), 6u);
  for (size_t i = 0; i < m.times_ns.size(); ++i) {
    EXPECT_GE(m.times_ns[i], start) << "kernel timestamps are CLOCK_MONOTONIC";
    if (i > 0) {
      EXPECT_GT(m.times_ns[i], m.times_ns[i - 1]);
    }
  }
  ASSERT_TRUE(driver->Blackout().ok());
  for (int c = 0; c < 3; ++c) EXPECT_EQ(sim.Value(c), 0);
}

// The node as the sync generator on gpio-sim: its clock line is an output the kernel holds. A planned run of 40 slots
// goes out; right after each write the line is read back through sysfs: every edge the driver wrote is a rise the
// kernel held, every row's lines hold the row; after the run the clock line is low and the channel lines hold the row
// of the last edge.
TEST(GpiodLightTest, GeneratesTheSlotClockOnGpioSimAndTheKernelHoldsEveryEdge) {
  if (std::string why = GpioSimChip::WhyNot(); !why.empty()) GTEST_SKIP() << why;
  GpioSimChip sim(8);
  ASSERT_TRUE(sim.ok()) << "could not make a gpio-sim chip";
  ReadBackLines* lines = nullptr;
  auto driver = ArmedOnSim(sim, "lights-gpio-sim-generator", 100, /*drives=*/true, &lines);
  ASSERT_NE(driver, nullptr);
  const PatternTable& table = Rows();
  v1::SlotClockRunRequest run;
  run.set_slots(40);
  run.set_lead_slots(20);
  auto started = driver->RunClock(run);
  ASSERT_TRUE(started.ok()) << started.status();
  for (int i = 0; i < 2000; ++i) {
    auto now = driver->ClockRun();
    if (now.ok() && now->current_slot() >= now->end_slot() - 1) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(20));  // the last pulse's low half
  const EdgeTiming t = driver->Edges().timing;
  EXPECT_EQ(t.count + t.lost_edges, 40u);
  EXPECT_EQ(lines->rises_written.load(), static_cast<int>(t.count));
  EXPECT_EQ(lines->rises_held.load(), lines->rises_written.load()) << "rises the kernel held, against edges written";
  EXPECT_EQ(lines->mismatches.load(), 0) << "channel lines the kernel held otherwise than the row written";
  EXPECT_EQ(sim.Value(7), 0) << "the clock line is low after the run";
  const uint64_t steps = driver->State().steps;
  ASSERT_GT(steps, 0u);
  const ChannelLevels& row = table.rows[static_cast<size_t>((steps - 1) % 3)];
  for (int c = 0; c < 3; ++c) EXPECT_EQ(sim.Value(c), row[static_cast<size_t>(c)] ? 1 : 0) << "channel " << c;
  ASSERT_TRUE(driver->Disarm().ok());
  for (int c = 0; c < 3; ++c) EXPECT_EQ(sim.Value(c), 0);
}

// The witness of an external generator on gpio-sim: the clock runs free on the input (the line's pull); the table
// waits, dark, for the planned edge; the node numbers the edges it saw and reports the one its table started on.
TEST(GpiodLightTest, OnAFreeRunningGpioSimInputTheTableStartsAtThePlannedEdge) {
  if (std::string why = GpioSimChip::WhyNot(); !why.empty()) GTEST_SKIP() << why;
  GpioSimChip sim(8);
  ASSERT_TRUE(sim.ok()) << "could not make a gpio-sim chip";
  // Edges made by hand, 10 ms apart or more on a busy machine: a 1 Hz clock, so that no gap reads as edges lost.
  auto driver = ArmedOnSim(sim, "lights-gpio-sim-witness", 1, /*drives=*/false);
  ASSERT_NE(driver, nullptr);
  const PatternTable& table = Rows();
  ASSERT_TRUE(driver->StartAt(kStartNotYet).ok());
  auto edge = [&](int n) {
    for (int i = 0; i < n; ++i) {
      ASSERT_TRUE(sim.Pull(7, true));
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
      ASSERT_TRUE(sim.Pull(7, false));
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
  };
  edge(3);
  auto in = driver->SlotClockInput();
  for (int i = 0; i < 500 && in.ok() && driver->Edges().timing.count < 3; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
    in = driver->SlotClockInput();
  }
  ASSERT_TRUE(in.ok()) << in.status();
  EXPECT_EQ(driver->State().steps, 0u) << "dark until its planned edge";
  for (int c = 0; c < 3; ++c) EXPECT_EQ(sim.Value(c), 0);
  // An edge that has passed cannot be the first. The planned edge: a period (1 s) after the last one seen; the table
  // starts on the first edge at or after half a period before it, so the test makes its next edges after that (the
  // pulls are not a clock): they step rows 0 and 1. The same request again (a retry) changes nothing.
  EXPECT_TRUE(absl::IsFailedPrecondition(driver->StartAt(in->last_edge_ns)));
  const int64_t plan = in->last_edge_ns + 1'000'000'000;
  ASSERT_TRUE(driver->StartAt(plan).ok());
  ASSERT_TRUE(driver->StartAt(plan).ok());
  EXPECT_EQ(driver->State().steps, 0u);
  while (timing::HostClockNs(true) < plan - 450'000'000) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  edge(2);
  for (int i = 0; i < 500 && driver->State().steps < 2; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  EXPECT_EQ(driver->State().steps, 2u);
  for (int c = 0; c < 3; ++c) EXPECT_EQ(sim.Value(c), table.rows[1][static_cast<size_t>(c)] ? 1 : 0);
  in = driver->SlotClockInput();
  ASSERT_TRUE(in.ok());
  EXPECT_EQ(in->table_first_slot, in->last_slot - 1);
  ASSERT_TRUE(driver->Disarm().ok());
}

TEST(GpiodLightTest, GeneratesTheSlotClockOnARealChip) {
  const char* chip = std::getenv("FASTAGE_GPIO_CHIP");
  const char* lines = std::getenv("FASTAGE_GPIO_LINES");
  if (chip == nullptr || lines == nullptr) {
    GTEST_SKIP() << "no real GPIO chip named: set FASTAGE_GPIO_CHIP and FASTAGE_GPIO_LINES (\"4,5,6:7\": free "
                    "output lines, then the slot clock line) to run on one";
  }
  std::vector<std::string> parts = absl::StrSplit(lines, ':');
  ASSERT_EQ(parts.size(), 2u) << "FASTAGE_GPIO_LINES is \"outputs:clock\"";
  GpiodDriverOptions o;
  o.node_id = "lights-gpio-hw";
  o.lines.chip = chip;
  for (absl::string_view s : absl::StrSplit(parts[0], ',')) {
    uint32_t line = 0;
    ASSERT_TRUE(absl::SimpleAtoi(s, &line)) << s;
    o.lines.outputs.push_back(line);
  }
  uint32_t clock = 0;
  ASSERT_TRUE(absl::SimpleAtoi(parts[1], &clock));
  o.lines.slot_clock_line = clock;
  o.lines.drives_slot_clock = true;
  o.channel_count = static_cast<uint32_t>(o.lines.outputs.size());
  auto driver = GpiodLightDriver::Open(o);
  ASSERT_TRUE(driver.ok()) << driver.status();
  ASSERT_TRUE((*driver)
                  ->LoadPatternTable(
                      {"t", {"on", "off"}, {ChannelLevels(o.channel_count, 65535), ChannelLevels(o.channel_count, 0)}})
                  .ok());
  ASSERT_TRUE((*driver)->Arm().ok());
  // A run of 300 slots, as the controller asks the sync generator for a take's.
  v1::SlotClockRunRequest run;
  run.set_slots(300);
  run.set_lead_slots(10);
  auto started = (*driver)->RunClock(run);
  ASSERT_TRUE(started.ok()) << started.status();
  for (int i = 0; i < 1000; ++i) {
    auto now = (*driver)->ClockRun();
    if (now.ok() && now->current_slot() >= now->end_slot() - 1) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  ASSERT_TRUE((*driver)->Disarm().ok());
  EdgeTiming t = (*driver)->Edges().timing;
  EXPECT_EQ(t.count + t.lost_edges, 300u);
  EXPECT_EQ((*driver)->State().steps, t.count);
  std::printf("%s: %llu edges, period %.3f us (nominal %.3f), worst deviation %.1f us, edge to outputs %.1f us\n", chip,
              static_cast<unsigned long long>(t.count), t.period_mean_ns / 1e3, 1e6 / 912,
              t.period_max_deviation_ns / 1e3, t.max_step_latency_ns / 1e3);
}

}  // namespace
}  // namespace stage::light
