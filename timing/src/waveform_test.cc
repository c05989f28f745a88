// Waveform export: the VCD's edges are the schedule's, rounded to the timescale; the SVG marks violations.
#include "stage/timing/waveform.h"

#include <map>
#include <sstream>

#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/timing/schedule.h"
#include "stage/timing/verifier.h"

namespace stage::timing {
namespace {

using ::testing::HasSubstr;

v1::TimingReport ShippedReport(void (*edit)(v1::RigConfig*) = nullptr) {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok());
  if (edit != nullptr) edit(&rig->rig);
  auto report = CheckRigTiming(rig->rig, rig->base_dir);
  EXPECT_TRUE(report.ok()) << report.status();
  return *report;
}

// A small VCD reader for the test: signal name -> (time, value) changes, including the $dumpvars values.
struct Vcd {
  std::string timescale;
  std::map<std::string, std::vector<std::pair<int64_t, int>>> changes;
  int64_t end = 0;
};

Vcd ReadVcd(const std::string& text) {
  Vcd vcd;
  std::map<std::string, std::string> names;  // code -> name
  std::istringstream in(text);
  std::string line;
  int64_t now = 0;
  bool header = true;
  while (std::getline(in, line)) {
    if (header) {
      if (absl::StartsWith(line, "$timescale")) vcd.timescale = line;
      if (absl::StartsWith(line, "$var")) {
        std::vector<std::string> f = absl::StrSplit(line, ' ', absl::SkipEmpty());
        // $var wire 1 <code> <ref> [<bit>] $end
        std::string name = f[4];
        if (f.size() == 7) name += f[5];
        names[f[3]] = name;
      }
      if (absl::StartsWith(line, "$enddefinitions")) header = false;
      continue;
    }
    if (line.empty() || line[0] == '$') continue;
    if (line[0] == '#') {
      now = std::stoll(line.substr(1));
      vcd.end = now;
      continue;
    }
    vcd.changes[names.at(line.substr(1))].push_back({now, line[0] - '0'});
  }
  return vcd;
}

std::vector<int64_t> Rises(const Vcd& vcd, const std::string& name) {
  std::vector<int64_t> out;
  for (const auto& [t, v] : vcd.changes.at(name)) {
    if (v == 1) out.push_back(t);
  }
  return out;
}

TEST(VcdTest, OneFrameOfTheShippedRigHasTheScheduledEdges) {
  v1::TimingReport report = ShippedReport();
  const v1::Schedule& s = report.schedule();
  const TimeBase base = TimeBase::FromProto(s.time_base());
  auto text = ScheduleToVcd(s, {0, 38});
  ASSERT_TRUE(text.ok()) << text.status();
  Vcd vcd = ReadVcd(*text);
  EXPECT_EQ(vcd.timescale, "$timescale 1 ns $end");
  EXPECT_EQ(vcd.end, base.TicksToNs(base.SlotStartTicks(38)));  // 41666667 ns

  // Slot clock: high from every slot edge, each edge the exact time rounded to the nanosecond.
  std::vector<int64_t> rises = Rises(vcd, "slot_clock");
  ASSERT_EQ(rises.size(), 38u);
  for (int k = 0; k < 38; ++k) EXPECT_EQ(rises[k], base.SlotStartNs(k)) << k;
  EXPECT_EQ(rises[1], 1'096'491);
  EXPECT_EQ(rises[3], 3'289'474);

  // The pattern bus carries the slot's pattern index from its edge.
  auto bus_at = [&](int64_t t) {
    int value = 0;
    for (int b = 0; b < 6; ++b) {
      int bit = 0;
      for (const auto& [when, v] : vcd.changes.at("pattern_id[" + std::to_string(b) + "]")) {
        if (when <= t) bit = v;
      }
      value |= bit << b;
    }
    return value;
  };
  for (int k = 0; k < 38; ++k) EXPECT_EQ(bus_at(base.SlotStartNs(k) + 1), k) << k;

  // High-speed cameras expose in every slot from 55 us after the edge for 900 us.
  std::vector<int64_t> hs = Rises(vcd, "hs_1_exposure");
  ASSERT_EQ(hs.size(), 38u);
  for (int k = 0; k < 38; ++k) {
    EXPECT_EQ(hs[k], base.TicksToNs(base.SlotStartTicks(k) + base.UsToTicks(55))) << k;
  }
  // Machine-vision cameras only in slot 19, the parallel full-on slot.
  std::vector<int64_t> mv = Rises(vcd, "mv_01_exposure");
  ASSERT_EQ(mv.size(), 1u);
  EXPECT_EQ(mv[0], base.TicksToNs(base.SlotStartTicks(19) + base.UsToTicks(55)));
  EXPECT_EQ(Rises(vcd, "mv_01_trigger"), mv);
  EXPECT_EQ(Rises(vcd, "clock_div38_phase19"), std::vector<int64_t>{base.SlotStartNs(19)});
  // The readout of slot -1 is still running when the window opens.
  EXPECT_EQ(vcd.changes.at("hs_1_readout").front(), (std::pair<int64_t, int>{0, 1}));
  // Light node switching: 20 us to 55 us after each edge.
  std::vector<int64_t> step = Rises(vcd, "lights_modbus_3_step");
  ASSERT_EQ(step.size(), 38u);
  EXPECT_EQ(step[5], base.TicksToNs(base.SlotStartTicks(5) + base.UsToTicks(20)));
}

TEST(VcdTest, FinerTimescaleAndLateWindows) {
  v1::TimingReport report = ShippedReport();
  const TimeBase base = TimeBase::FromProto(report.schedule().time_base());
  auto text = ScheduleToVcd(report.schedule(), {10'000'000, 2}, {.timescale_fs = 1000});
  ASSERT_TRUE(text.ok()) << text.status();
  Vcd vcd = ReadVcd(*text);
  EXPECT_EQ(vcd.timescale, "$timescale 1 ps $end");
  // Slot 10^7 + 1 starts at (10^7 + 1) / 912 s = 10964913377192.982... ns.
  std::vector<int64_t> rises = Rises(vcd, "slot_clock");
  ASSERT_EQ(rises.size(), 2u);
  EXPECT_EQ(rises[0], base.TicksToUnits(base.SlotStartTicks(10'000'000), 1000));
  EXPECT_EQ(rises[1], 10'964'913'377'192'982);
}

TEST(VcdTest, SameScheduleSameFile) {
  v1::TimingReport report = ShippedReport();
  auto a = ScheduleToVcd(report.schedule(), {0, 38});
  auto b = ScheduleToVcd(ShippedReport().schedule(), {0, 38});
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(*a, *b);
  EXPECT_THAT(*a, HasSubstr(report.schedule().hash()));
}

TEST(VcdTest, NamesAreVerilogIdentifiers) {
  EXPECT_EQ(VcdName("mv-01_exposure"), "mv_01_exposure");
  EXPECT_EQ(VcdName("cam.a-1_trigger"), "cam_a_1_trigger");
  EXPECT_EQ(VcdName("pattern_id[3]"), "pattern_id[3]");
  EXPECT_EQ(VcdName("7up"), "_7up");
}

TEST(VcdTest, Timescales) {
  EXPECT_EQ(*ParseTimescale("1ns"), 1'000'000);
  EXPECT_EQ(*ParseTimescale("10 ps"), 10'000);
  EXPECT_EQ(*ParseTimescale("100us"), 100'000'000'000);
  EXPECT_EQ(*TimescaleName(1'000'000), "1 ns");
  EXPECT_FALSE(ParseTimescale("2ns").ok());
  EXPECT_FALSE(ParseTimescale("ns").ok());
  EXPECT_FALSE(ParseTimescale("1 parsec").ok());
  EXPECT_FALSE(ScheduleToVcd(ShippedReport().schedule(), {0, 0}).ok());
  EXPECT_FALSE(ScheduleToVcd(ShippedReport().schedule(), {0, 1}, {.timescale_fs = 3}).ok());
  // 1 ms cannot show a 10 us trigger pulse: refused, not drawn wrong.
  auto coarse = ScheduleToVcd(ShippedReport().schedule(), {0, 6}, {.timescale_fs = 1'000'000'000'000});
  ASSERT_FALSE(coarse.ok());
  EXPECT_THAT(coarse.status().message(), HasSubstr("timescale 1 ms is too coarse"));
  // 1 us still shows every pulse of the shipped rig.
  EXPECT_TRUE(ScheduleToVcd(ShippedReport().schedule(), {0, 38}, {.timescale_fs = 1'000'000'000}).ok());
}

TEST(SvgTest, LabelsPatternsAndMarksViolationsInRed) {
  v1::TimingReport clean = ShippedReport();
  auto svg = ReportToSvg(clean, {0, 38});
  ASSERT_TRUE(svg.ok()) << svg.status();
  EXPECT_THAT(*svg, HasSubstr("<svg xmlns=\"http://www.w3.org/2000/svg\""));
  EXPECT_THAT(*svg, HasSubstr("19 parallel-full"));
  EXPECT_THAT(*svg, HasSubstr("No violations."));
  EXPECT_THAT(*svg, ::testing::Not(HasSubstr("#e00000")));

  v1::TimingReport bad =
      ShippedReport([](v1::RigConfig* rig) { rig->mutable_cameras(24)->mutable_trigger()->set_delay_us(40); });
  ASSERT_EQ(bad.errors(), 1);
  svg = ReportToSvg(bad, {0, 38});
  ASSERT_TRUE(svg.ok());
  // hs-1 exposes early in every slot: 38 red marks, and the violation listed.
  size_t marks = 0;
  for (size_t at = svg->find("fill=\"#e00000\""); at != std::string::npos; at = svg->find("fill=\"#e00000\"", at + 1))
    ++marks;
  EXPECT_EQ(marks, 38u);
  EXPECT_THAT(*svg, HasSubstr("error [steady-light] hs-1 slot 0: exposure starts at 40.000 us"));
  // One slot: microsecond ticks and horizontal labels.
  svg = ReportToSvg(bad, {19, 1});
  ASSERT_TRUE(svg.ok());
  EXPECT_THAT(*svg, HasSubstr("slot 19: parallel-full"));
  EXPECT_THAT(*svg, HasSubstr(">1000 us</text>"));
}

}  // namespace
}  // namespace stage::timing
