// `stagectl timing` as hardware engineers run it, and the VCD it writes read back by a tool we did not write:
// sigrok-cli (libsigrok's VCD reader, Debian's sigrok-cli package). The edges sigrok reports must be the schedule's,
// to the VCD timescale.
#include <cmath>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"
#include "stage/timing/verifier.h"
#include "stage/timing/waveform.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

constexpr auto kTimeout = std::chrono::seconds(60);
constexpr const char* kSigrok = "/usr/bin/sigrok-cli";

// Changes per signal: name -> [(time in timescale units, value)], from a VCD of one-bit wires. Values at the first
// timestamp (the $dumpvars block, or sigrok's first line) count as changes at that time.
using Changes = std::map<std::string, std::vector<std::pair<int64_t, int>>>;

struct ParsedVcd {
  std::string timescale;
  Changes changes;
};

ParsedVcd ParseVcd(const std::string& text) {
  ParsedVcd vcd;
  std::map<std::string, std::string> names;
  bool header = true;
  int64_t now = 0;
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    if (header) {
      if (absl::StartsWith(line, "$timescale")) vcd.timescale = line;
      if (absl::StartsWith(line, "$var")) {
        std::vector<std::string> f = absl::StrSplit(line, ' ', absl::SkipEmpty());
        std::string name = f[4];
        if (f.size() == 7) name += f[5];  // "pattern_id [3]"
        names[f[3]] = name;
      }
      if (absl::StartsWith(line, "$enddefinitions")) header = false;
      continue;
    }
    // sigrok writes "#t v1! v2\"" on one line; ours writes one change per line.
    for (absl::string_view token : absl::StrSplit(line, ' ', absl::SkipEmpty())) {
      if (token.empty() || token[0] == '$') continue;
      if (token[0] == '#') {
        now = std::stoll(std::string(token.substr(1)));
        continue;
      }
      auto it = names.find(std::string(token.substr(1)));
      if (it == names.end()) continue;
      auto& list = vcd.changes[it->second];
      const int v = token[0] - '0';
      if (list.empty() || list.back().second != v) list.push_back({now, v});
    }
  }
  return vcd;
}

TEST(TimingCliTest, SigrokReadsTheVcdOfOneFrameWithTheScheduledEdges) {
  TempDir dir;
  const std::string vcd_path = dir.path() + "/frame.vcd";
  CommandResult exported = RunCommand(
      {"stagectl", "timing", "export", "--rig", "builtin:fastage", "--vcd", vcd_path, "--frames", "1"}, kTimeout);
  ASSERT_EQ(exported.exit.exit_code, 0) << exported.err;
  EXPECT_THAT(exported.err, HasSubstr("slots 0 to 37: 0 error(s), 0 warning(s)"));
  const std::string ours = ReadFile(vcd_path);
  ParsedVcd own = ParseVcd(ours);
  ASSERT_EQ(own.timescale, "$timescale 1 ns $end");

  // The channels sigrok sees.
  CommandResult show = RunCommand({kSigrok, "-I", "vcd", "-i", vcd_path, "--show"}, kTimeout);
  ASSERT_EQ(show.exit.exit_code, 0) << "sigrok-cli (Debian package sigrok-cli, installed by scripts/bootstrap): "
                                    << show.err;
  std::vector<std::string> channels;
  for (absl::string_view line : absl::StrSplit(show.out, '\n')) {
    if (absl::StartsWith(line, "- ") && absl::EndsWith(line, ": logic")) {
      channels.emplace_back(line.substr(2, line.size() - 2 - 7));
    }
  }
  // slot_clock, cycle_start, clock_div38_phase19, 6 pattern bits, steady_window, 6 light nodes, 27 cameras x 3.
  ASSERT_EQ(channels.size(), 97u) << show.out;
  EXPECT_THAT(show.out, HasSubstr("Samplerate: 1000000000"));

  // Edge times as sigrok sees them: its "timing" protocol decoder on every channel, annotating the time between
  // consecutive edges with their sample numbers (1 GHz samples = ns). Channel selection with -C and the VCD writer
  // (at most 94 channels) are not used: in libsigrok 0.5.2 -C on an input file mislabels the data.
  std::map<std::string, std::set<int64_t>> sigrok;  // channel -> edge times
  const size_t kPerRun = 25;
  for (size_t first = 0; first < channels.size(); first += kPerRun) {
    std::vector<std::string> argv = {kSigrok, "-I",         "vcd", "-i", vcd_path, "--protocol-decoder-samplenum",
                                     "-A",    "timing=time"};
    const size_t last = std::min(channels.size(), first + kPerRun);
    for (size_t i = first; i < last; ++i) {
      argv.push_back("-P");
      argv.push_back("timing:data=" + channels[i]);
    }
    CommandResult r = RunCommand(argv, kTimeout);
    ASSERT_EQ(r.exit.exit_code, 0) << r.err;
    // "55000-955000 timing-3: 900.000 us (1.111 kHz)": instance n is the n-th -P of this run.
    for (absl::string_view line : absl::StrSplit(r.out, '\n', absl::SkipEmpty())) {
      int64_t a = 0, b = 0;
      int n = 0;
      ASSERT_EQ(std::sscanf(std::string(line).c_str(), "%ld-%ld timing-%d:", &a, &b, &n), 3) << line;
      ASSERT_GE(n, 1);
      ASSERT_LE(static_cast<size_t>(n), last - first);
      sigrok[channels[first + n - 1]].insert({a, b});
    }
  }

  // 1. sigrok finds every edge of every signal where our file puts it. (The decoder reports intervals between
  //    edges, so a signal with a single edge in the window, cycle_start here, shows none.)
  int compared = 0;
  for (const auto& [name, list] : own.changes) {
    std::set<int64_t> edges;
    for (const auto& [t, v] : list) {
      if (t > 0) edges.insert(t);
    }
    if (edges.size() < 2) {
      EXPECT_TRUE(sigrok[name].empty()) << name;
      continue;
    }
    EXPECT_EQ(sigrok[name], edges) << name;
    ++compared;
  }
  EXPECT_EQ(compared, 95);  // all but cycle_start and pattern_id[5] (high from slot 32 on)

  // 2. Those edges are the schedule's, computed here from the compiled schedule, each within half a nanosecond of
  //    the exact time.
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  auto report = timing::CheckRigTiming(rig->rig, rig->base_dir);
  ASSERT_TRUE(report.ok());
  const v1::Schedule& s = report->schedule();
  const timing::TimeBase base = timing::TimeBase::FromProto(s.time_base());
  auto exact_ns = [&](int64_t ticks) { return static_cast<double>(ticks) / base.ticks_per_ns(); };
  auto expect_edge = [&](int64_t reported, int64_t ticks, const std::string& what) {
    EXPECT_LE(std::abs(static_cast<double>(reported) - exact_ns(ticks)), 0.5) << what;
  };
  auto edges = [&](const std::string& name) { return std::vector<int64_t>(sigrok[name].begin(), sigrok[name].end()); };
  // Slot clock: up at every edge, down half a slot later.
  std::vector<int64_t> clock = edges("slot_clock");
  ASSERT_EQ(clock.size(), 75u);  // 37 rises (slot 0's is at time 0) and 38 falls
  for (int k = 1; k < 38; ++k) {
    expect_edge(clock[2 * k - 1], base.SlotStartTicks(k), "slot_clock slot " + std::to_string(k));
    expect_edge(clock[2 * k - 2], base.SlotStartTicks(k - 1) + base.ticks_per_slot() / 2, "slot_clock fall");
  }
  // The pattern bus changes only at slot edges, and bit b toggles as the index counts.
  for (int b = 0; b < 6; ++b) {
    const std::string name = "pattern_id[" + std::to_string(b) + "]";
    std::set<int64_t> expected;
    for (int k = 1; k < 38; ++k) {
      if (((k >> b) & 1) != (((k - 1) >> b) & 1)) expected.insert(base.TicksToNs(base.SlotStartTicks(k)));
    }
    if (expected.size() >= 2) {
      EXPECT_EQ(sigrok[name], expected) << name;
    } else {
      EXPECT_TRUE(sigrok[name].empty()) << name;
    }
  }
  for (const v1::LightNodeTiming& n : s.light_nodes()) {
    std::vector<int64_t> steps = edges(timing::VcdName(n.id() + "_step"));
    ASSERT_EQ(steps.size(), 76u) << n.id();
    for (int k = 0; k < 38; ++k) {
      expect_edge(steps[2 * k], base.SlotStartTicks(k) + n.switch_ticks(), n.id() + " switch");
      expect_edge(steps[2 * k + 1], base.SlotStartTicks(k) + n.steady_start_ticks(), n.id() + " steady");
    }
  }
  for (const v1::CameraTiming& c : s.cameras()) {
    std::vector<int64_t> fired;
    for (int64_t k = 0; k < 38; ++k) {
      if (timing::FiresInSlot(c, k)) fired.push_back(k);
    }
    std::vector<int64_t> trigger = edges(timing::VcdName(c.id() + "_trigger"));
    std::vector<int64_t> exposure = edges(timing::VcdName(c.id() + "_exposure"));
    ASSERT_EQ(trigger.size(), 2 * fired.size()) << c.id();
    ASSERT_EQ(exposure.size(), 2 * fired.size()) << c.id();
    for (size_t i = 0; i < fired.size(); ++i) {
      const int64_t start = base.SlotStartTicks(fired[i]);
      expect_edge(trigger[2 * i], start + c.trigger_ticks(), c.id() + " trigger");
      expect_edge(trigger[2 * i + 1], start + c.trigger_ticks() + c.trigger_pulse_ticks(), c.id() + " trigger end");
      expect_edge(exposure[2 * i], start + c.trigger_ticks(), c.id() + " exposure start");
      expect_edge(exposure[2 * i + 1], start + c.trigger_ticks() + c.exposure_ticks(), c.id() + " exposure end");
    }
  }
  EXPECT_EQ(edges("mv_17_exposure").size(), 2u);
  EXPECT_EQ(edges("hs_2_exposure").size(), 76u);
}

TEST(TimingCliTest, CheckShowAndWhatIf) {
  CommandResult ok = RunCommand({"stagectl", "timing", "check", "--rig", "builtin:fastage"}, kTimeout);
  EXPECT_EQ(ok.exit.exit_code, 0) << ok.err;
  EXPECT_THAT(ok.out, HasSubstr("0 error(s), 0 warning(s): the schedule may be armed"));

  // What if the LEDs took 250 us to settle? The triggers follow the light (55 -> 275 us), so the 900 us exposures
  // run into the next pattern.
  CommandResult late = RunCommand(
      {"stagectl", "timing", "check", "--rig", "builtin:fastage", "--set", "timing.led_settle_us=250"}, kTimeout);
  EXPECT_EQ(late.exit.exit_code, 3) << late.err;
  EXPECT_THAT(late.out, HasSubstr("with timing.led_settle_us=250"));
  EXPECT_THAT(late.out, HasSubstr("error   steady-light    mv-01 slot 19: exposure ends at 1175.000 us"));
  EXPECT_THAT(late.out, HasSubstr("fix: shorten cameras[mv-01].exposure_us to <= 821.491"));
  EXPECT_THAT(late.out, HasSubstr("27 error(s), 0 warning(s): nothing arms"));

  CommandResult json = RunCommand(
      {"stagectl", "timing", "check", "--rig", "builtin:fastage", "--json", "--set", "cameras[mv-*].link=gige-1"},
      kTimeout);
  EXPECT_EQ(json.exit.exit_code, 0) << json.err;
  EXPECT_THAT(json.out, HasSubstr("\"check\": \"link-bandwidth\""));
  EXPECT_THAT(json.out, HasSubstr("\"warnings\": 24"));

  CommandResult show = RunCommand({"stagectl", "timing", "show", "--rig", "builtin:fastage"}, kTimeout);
  EXPECT_EQ(show.exit.exit_code, 0) << show.err;
  EXPECT_THAT(show.out, HasSubstr("light steady from 55.000 us"));
  EXPECT_THAT(show.out, HasSubstr("19 parallel-full"));
  EXPECT_THAT(show.out, HasSubstr("48 Hz 0.47 %"));

  TempDir dir;
  CommandResult svg = RunCommand({"stagectl", "timing", "export", "--rig", "builtin:fastage", "--svg",
                                  dir.path() + "/slot.svg", "--slots", "19:20", "--json", dir.path() + "/slot.json"},
                                 kTimeout);
  EXPECT_EQ(svg.exit.exit_code, 0) << svg.err;
  EXPECT_THAT(ReadFile(dir.path() + "/slot.svg"), HasSubstr("slot 19: parallel-full"));
  EXPECT_THAT(ReadFile(dir.path() + "/slot.json"), HasSubstr("\"slot_count\": \"1\""));
}

TEST(TimingCliTest, BadInputIsOneLineNamingIt) {
  auto one_line = [](const CommandResult& r, int code, const std::string& text) {
    EXPECT_EQ(r.exit.exit_code, code) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_THAT(r.err, HasSubstr(text));
  };
  one_line(RunCommand({"stagectl", "timing", "check", "--rig", "builtin:fastage", "--set", "cameras[hs-9].gain_db=1"},
                      kTimeout),
           2, "no cameras entry with id \"hs-9\"");
  one_line(RunCommand({"stagectl", "timing", "check", "--rig", "builtin:fastage", "--set", "timing.slot_rate_hz=912.5"},
                      kTimeout),
           2, "timing.slot_rate_hz: 912.5 is not a whole number");
  one_line(RunCommand({"stagectl", "timing", "export", "--rig", "builtin:fastage"}, kTimeout), 2,
           "needs at least one of --vcd, --svg, --json");
  one_line(
      RunCommand({"stagectl", "timing", "export", "--rig", "builtin:fastage", "--vcd", "/tmp/x.vcd", "--slots", "9:3"},
                 kTimeout),
      2, "--slots 9:3 is not FIRST:END");
  one_line(RunCommand({"stagectl", "timing", "export", "--rig", "builtin:fastage", "--vcd", "/tmp/x.vcd", "--timescale",
                       "3ns"},
                      kTimeout),
           2, "timescale \"3ns\"");
  one_line(RunCommand({"stagectl", "timing", "show", "--rig", "/nonexistent.yaml"}, kTimeout), 2,
           "/nonexistent.yaml: cannot read rig file");
}

}  // namespace
}  // namespace stage::testing
