// The verifier: the shipped rig passes; each constraint is caught by a rig broken in that one way, with the device,
// the slot and the numbers in the message.
#include "stage/timing/verifier.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <map>

#include "absl/strings/match.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/timing/schedule.h"

namespace stage::timing {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

v1::TimingReport Verify(const std::function<void(v1::RigConfig*)>& edit = {}, const std::string& base_dir = ".") {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok()) << rig.status();
  if (edit) edit(&rig->rig);
  // What-if edits must still be a valid rig.
  std::vector<RigError> errors = ValidateRig(rig->rig, base_dir);
  for (const auto& e : errors) ADD_FAILURE() << e.path << ": " << e.message;
  auto report = CheckRigTiming(rig->rig, base_dir);
  EXPECT_TRUE(report.ok()) << report.status();
  return report.ok() ? *report : v1::TimingReport();
}

std::vector<v1::Violation> Of(const v1::TimingReport& report, absl::string_view check) {
  std::vector<v1::Violation> out;
  for (const auto& v : report.violations()) {
    if (v.check() == check) out.push_back(v);
  }
  return out;
}

std::string Dump(const v1::TimingReport& report) {
  std::vector<std::string> lines;
  for (const auto& v : report.violations()) {
    lines.push_back(absl::StrCat(SeverityName(v.severity()), " ", v.check(), " ", v.device(), " slot ", v.slot(), ": ",
                                 v.message(), " -- fix: ", v.fix()));
  }
  return absl::StrJoin(lines, "\n");
}

v1::CameraConfig* Camera(v1::RigConfig* rig, const std::string& id) {
  for (auto& c : *rig->mutable_cameras()) {
    if (c.id() == id) return &c;
  }
  ADD_FAILURE() << "no camera " << id;
  return rig->mutable_cameras(0);
}

TEST(VerifierTest, ShippedRigPassesWithoutWarnings) {
  v1::TimingReport report = Verify();
  EXPECT_EQ(report.errors(), 0) << Dump(report);
  EXPECT_EQ(report.warnings(), 0) << Dump(report);
  // The figures behind that: the flicker components below 60 Hz and every budget are reported.
  ASSERT_EQ(report.flicker_size(), 2);  // 24 and 48 Hz
  EXPECT_NEAR(report.flicker(0).frequency_hz(), 24, 1e-9);
  EXPECT_LT(report.flicker(0).modulation(), 1e-9);  // both blocks in the same order: no 24 Hz component
  EXPECT_NEAR(report.flicker(1).frequency_hz(), 48, 1e-9);
  EXPECT_LT(report.flicker(1).modulation(), report.flicker(1).warn_modulation());
  int links = 0, rams = 0, disks = 0, leds = 0;
  for (const auto& f : report.loads()) {
    links += f.kind() == "link";
    rams += f.kind() == "ram";
    disks += f.kind() == "disk";
    leds += f.kind() == "led";
    EXPECT_LE(f.used(), f.budget()) << f.kind() << " " << f.device();
  }
  EXPECT_EQ(links, 24);
  EXPECT_EQ(rams, 3);
  EXPECT_EQ(disks, 4);  // rec-1..rec-4; the high-speed cameras record to RAM
  EXPECT_EQ(leds, 6);
}

TEST(VerifierTest, ShippedRigOnOneGigEGetsOnlyTheLinkWarning) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    for (auto& c : *rig->mutable_cameras()) {
      if (c.role() == v1::CAMERA_ROLE_MACHINE_VISION) c.set_link(v1::LINK_KIND_GIGE_1);
    }
  });
  EXPECT_EQ(report.errors(), 0) << Dump(report);
  auto links = Of(report, kCheckLinkBandwidth);
  EXPECT_EQ(links.size(), 24u);
  EXPECT_EQ(report.warnings(), 24) << Dump(report);
  ASSERT_FALSE(links.empty());
  EXPECT_EQ(links[0].device(), "mv-01");
  EXPECT_EQ(links[0].severity(), v1::SEVERITY_WARNING);
  // 2592 x 2048 x 24 = 127.4 MB/s of pixels; with the shipped jumbo frames, per frame 593 packets of 8964 payload
  // bytes, 9038 bytes each on the wire, plus leader and trailer: 128.6 MB/s.
  EXPECT_THAT(links[0].message(),
              AllOf(HasSubstr("127.4 MB/s of frames"), HasSubstr("2592x2048 bayer-rg8 at 24 fps"),
                    HasSubstr("128.6 MB/s on the link"), HasSubstr("packet size 9000"),
                    HasSubstr("a 1 GigE link carries 125.0"), HasSubstr("34 MiB by the end of a 10 s take"),
                    HasSubstr("frame_buffer_mib not declared")));
  // 2048 rows * 125.0 / 128.6 = 1990 rows fit.
  EXPECT_THAT(links[0].fix(), AllOf(HasSubstr("2.5/5/10 GigE"), HasSubstr("<= 1990 rows")));
}

TEST(VerifierTest, OneGigEWithoutJumboFrames) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    Camera(rig, "mv-13")->set_link(v1::LINK_KIND_GIGE_1);
    Camera(rig, "mv-13")->set_packet_size(1500);
  });
  auto links = Of(report, kCheckLinkBandwidth);
  ASSERT_EQ(links.size(), 1u) << Dump(report);
  EXPECT_EQ(links[0].device(), "mv-13");
  // Per frame 3626 packets of 1464 payload bytes, 1538 bytes each on the wire: 133.8 MB/s.
  EXPECT_THAT(links[0].message(), AllOf(HasSubstr("133.8 MB/s on the link"), HasSubstr("packet size 1500"),
                                        HasSubstr("80 MiB by the end of a 10 s take")));
  EXPECT_THAT(links[0].fix(), AllOf(HasSubstr("<= 1912 rows"),
                                    HasSubstr("jumbo frames (packet_size 9000: 128.6 MB/s) are not enough")));
}

TEST(VerifierTest, LinkOverBudgetWithADeclaredFrameBuffer) {
  v1::TimingReport small = Verify([](v1::RigConfig* rig) {
    Camera(rig, "mv-07")->set_link(v1::LINK_KIND_GIGE_1);
    Camera(rig, "mv-07")->set_frame_buffer_mib(32);
  });
  auto v = Of(small, kCheckLinkBandwidth);
  ASSERT_EQ(v.size(), 1u) << Dump(small);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_EQ(v[0].device(), "mv-07");
  // Backlog grows at (128.6 - 125) / 128.6 of 127.4 MB/s = 3.6 MB/s: 32 MiB last 9.32 s of the 10 s take.
  EXPECT_THAT(v[0].message(),
              AllOf(HasSubstr("32 MiB frame buffer overflows 9.32 s"), HasSubstr("34 MiB by the end of 10 s")));

  v1::TimingReport big = Verify([](v1::RigConfig* rig) {
    Camera(rig, "mv-07")->set_link(v1::LINK_KIND_GIGE_1);
    Camera(rig, "mv-07")->set_frame_buffer_mib(512);
  });
  v = Of(big, kCheckLinkBandwidth);
  ASSERT_EQ(v.size(), 1u) << Dump(big);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_WARNING);
  // 34 MiB drain over the 125 MB/s link in 0.29 s.
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("512 MiB frame buffer absorbs the 34 MiB backlog"),
                                    HasSubstr("arrive 0.29 s after the take")));
}

TEST(VerifierTest, ExposureBeforeTheLightIsSteady) {
  v1::TimingReport report =
      Verify([](v1::RigConfig* rig) { Camera(rig, "hs-1")->mutable_trigger()->set_delay_us(40); });
  auto v = Of(report, kCheckSteadyLight);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_EQ(v[0].device(), "hs-1");
  EXPECT_EQ(v[0].slot(), 0);
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("starts at 40.000 us"), HasSubstr("slot 0 (cross-full)"),
                                    HasSubstr("steady at 55.000 us"),
                                    HasSubstr("switch 20.000 + rise/fall 5.000 + "
                                              "settle 30.000 us")));
  EXPECT_THAT(v[0].fix(), HasSubstr("trigger.delay_us >= 55.000"));
}

TEST(VerifierTest, ExposureIntoTheNextPattern) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { Camera(rig, "mv-03")->set_exposure_us(1050); });
  auto v = Of(report, kCheckSteadyLight);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].device(), "mv-03");
  EXPECT_EQ(v[0].slot(), 19);
  // 55 + 1050 = 1105 us; the last moment is 1096.491 + 20 - 20 us.
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("ends at 1105.000 us"), HasSubstr("slot 19 (parallel-full)"),
                                    HasSubstr("8.509 us after the last moment it may: 1096.491 us")));
  EXPECT_THAT(v[0].fix(), HasSubstr("exposure_us to <= 1041.491"));
}

TEST(VerifierTest, LightThatNeverSettles) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    rig->mutable_light_nodes(1)->set_switch_delay_us(20);
    rig->mutable_timing()->set_led_settle_us(1100);
  });
  auto v = Of(report, kCheckSlotTiming);
  ASSERT_EQ(v.size(), 6u) << Dump(report);
  EXPECT_EQ(v[0].device(), "lights-modbus-1");
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("never settles"), HasSubstr("settle 1100.000 us = 1125.000 us"),
                                    HasSubstr("next switch at 1116.491 us")));
  EXPECT_GT(report.errors(), 6);  // and every camera's exposure with it
}

TEST(VerifierTest, TriggeredFasterThanTheCameraCan) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { Camera(rig, "hs-2")->set_max_frame_rate_hz(800); });
  auto v = Of(report, kCheckFrameRate);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_EQ(v[0].device(), "hs-2");
  EXPECT_EQ(v[0].slot(), 0);
  EXPECT_THAT(v[0].message(),
              AllOf(HasSubstr("triggered at 912 Hz"), HasSubstr("4096x2304"), HasSubstr("at most 800 fps")));
  // The divider proposed keeps the camera on its patterns (2 divides the 38-pattern cycle), with its frame rate.
  EXPECT_EQ(v[0].fix(), "set cameras[hs-2].trigger.divider: 2 (and frame_rate_hz: 456), or reduce the ROI (height)");
}

TEST(VerifierTest, ReadoutLongerThanThePeriod) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { Camera(rig, "hs-3")->set_readout_us(1200); });
  auto v = Of(report, kCheckFrameRate);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].device(), "hs-3");
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("readout 1200.000 us"), HasSubstr("trigger period 1096.491 us")));
}

TEST(VerifierTest, FrameRateSettingThatDisagreesWithTheTriggers) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { Camera(rig, "mv-10")->set_frame_rate_hz(30); });
  auto v = Of(report, kCheckFrameRate);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_WARNING);
  EXPECT_EQ(v[0].device(), "mv-10");
  EXPECT_EQ(v[0].slot(), 19);
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("frame_rate_hz is 30"), HasSubstr("every 38 slot(s) = 24 Hz")));
  EXPECT_THAT(v[0].fix(), HasSubstr("frame_rate_hz: 24"));
}

TEST(VerifierTest, TriggerDuringReadoutWithoutOverlap) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    Camera(rig, "hs-1")->set_readout_us(500);
    Camera(rig, "hs-1")->set_overlap_exposure_readout(false);
  });
  auto v = Of(report, kCheckTriggerOverlap);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].device(), "hs-1");
  EXPECT_EQ(v[0].slot(), 1);
  EXPECT_THAT(v[0].message(),
              AllOf(HasSubstr("trigger of slot 1 comes 196.491 us into the readout of slot 0"),
                    HasSubstr("exposure 900.000 + readout 500.000 = 1400.000 us > trigger period 1096.491 us")));
  EXPECT_THAT(v[0].fix(), AllOf(HasSubstr("overlap_exposure_readout: true"), HasSubstr("exposure_us to <= 596.491")));
  // With overlapped exposure the same camera is fine.
  v1::TimingReport ok = Verify([](v1::RigConfig* rig) { Camera(rig, "hs-1")->set_readout_us(500); });
  EXPECT_TRUE(Of(ok, kCheckTriggerOverlap).empty()) << Dump(ok);
}

TEST(VerifierTest, TriggerPulseWiderThanThePeriod) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { rig->mutable_timing()->set_trigger_pulse_us(1100); });
  auto v = Of(report, kCheckTriggerOverlap);
  ASSERT_EQ(v.size(), 3u) << Dump(report);  // the high-speed cameras, triggered every slot
  EXPECT_EQ(v[0].device(), "hs-1");
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("pulse 1100.000 us"), HasSubstr("never returns low")));
}

TEST(VerifierTest, HighSpeedRamAgainstTheTakeLength) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { rig->mutable_timing()->set_take_length_s(40); });
  auto v = Of(report, kCheckCameraRam);
  ASSERT_EQ(v.size(), 3u) << Dump(report);
  EXPECT_EQ(v[0].device(), "hs-1");
  // 256 GiB / 9437184 bytes = 29127 frames = 31.94 s at 912 fps.
  EXPECT_EQ(v[0].slot(), 29127);
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("a 40 s take is 36480 frames x 9.44 MB"),
                                    HasSubstr("holds 256 GiB = 29127 frames = 31.94 s")));
  EXPECT_THAT(v[0].fix(), HasSubstr("take_length_s to <= 31.94 s"));
}

TEST(VerifierTest, AFreeRunningHighSpeedCameraFillsItsRamAtItsOwnRate) {
  // 500 fps free run for a 40 s take: 20000 frames x 9.44 MB = 175.8 GiB, within 256 GiB (912 fps would not be).
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    rig->mutable_timing()->set_take_length_s(40);
    Camera(rig, "hs-1")->mutable_trigger()->set_source(v1::TRIGGER_SOURCE_FREE_RUN);
    Camera(rig, "hs-1")->set_frame_rate_hz(500);
  });
  for (const auto& v : Of(report, kCheckCameraRam)) EXPECT_NE(v.device(), "hs-1") << Dump(report);
  EXPECT_EQ(Of(report, kCheckCameraRam).size(), 2u) << Dump(report);  // hs-2 and hs-3 still do not fit
  for (const auto& f : report.loads()) {
    if (f.kind() == "ram" && f.device() == "hs-1") {
      EXPECT_NEAR(f.used(), 20000 * 9437184.0 / (1 << 30), 0.01);
    }
  }
}

TEST(VerifierTest, RecordingHostDiskRate) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { rig->mutable_storage()->set_host_write_mb_per_s(700); });
  auto v = Of(report, kCheckDiskWrite);
  ASSERT_EQ(v.size(), 4u) << Dump(report);
  EXPECT_EQ(v[0].device(), "rec-1");
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  // Six machine-vision cameras at 127.4 MB/s.
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("writes 764.4 MB/s for 6 camera(s)"), HasSubstr("mv-01"),
                                    HasSubstr("sustains 700 MB/s")));
}

TEST(VerifierTest, LedDutyCycleOverTheLimit) {
  v1::TimingReport report =
      Verify([](v1::RigConfig* rig) { rig->mutable_light_nodes(4)->mutable_unit_limits()->set_max_duty_cycle(0.2); });
  auto v = Of(report, kCheckLedDuty);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_THAT(v[0].device(), HasSubstr("lights-gpio-1/ch"));
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("40 channel(s) of lights-gpio-1"), HasSubstr("over the 38-pattern cycle"),
                                    HasSubstr("limit max_duty_cycle 0.2")));
  EXPECT_TRUE(Of(report, kCheckLedThermal).empty()) << Dump(report);
}

TEST(VerifierTest, LedThermalBudgetWithAShortTimeConstant) {
  // The cycle averages about 0.25 of full drive per emitter, but the cross emitters are driven for the first 19
  // slots (20.8 ms) in a row: with a 5 ms time constant their load climbs well above the average.
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    auto* limits = rig->mutable_light_nodes(0)->mutable_unit_limits();
    limits->set_thermal_time_constant_s(0.005);
    limits->set_max_duty_cycle(0.45);
  });
  EXPECT_TRUE(Of(report, kCheckLedDuty).empty()) << Dump(report);
  auto v = Of(report, kCheckLedThermal);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_THAT(v[0].device(), HasSubstr("lights-modbus-1/ch"));
  EXPECT_THAT(v[0].message(),
              AllOf(HasSubstr("of lights-modbus-1 exceed their thermal budget"),
                    HasSubstr("thermal_time_constant_s 0.005"), HasSubstr("limit max_duty_cycle 0.45")));
  // A long time constant averages it out.
  v1::TimingReport ok =
      Verify([](v1::RigConfig* rig) { rig->mutable_light_nodes(0)->mutable_unit_limits()->set_max_duty_cycle(0.45); });
  EXPECT_TRUE(Of(ok, kCheckLedThermal).empty()) << Dump(ok);
}

// fastage-38 in textbook order (gradients, then complements): the order the shipped set avoids.
std::string TextbookOrderSet() {
  const std::vector<std::pair<const char*, const char*>> patterns = {
      {"full", "1"},           {"x+", "(1 + x) / 2"}, {"x-", "(1 - x) / 2"},   {"y+", "(1 + y) / 2"},
      {"y-", "(1 - y) / 2"},   {"z+", "(1 + z) / 2"}, {"z-", "(1 - z) / 2"},   {"xx", "x^2"},
      {"xx-c", "1 - x^2"},     {"yy", "y^2"},         {"yy-c", "1 - y^2"},     {"zz", "z^2"},
      {"zz-c", "1 - z^2"},     {"xy", "0.5 + x * y"}, {"xy-c", "0.5 - x * y"}, {"yz", "0.5 + y * z"},
      {"yz-c", "0.5 - y * z"}, {"xz", "0.5 + x * z"}, {"xz-c", "0.5 - x * z"}};
  std::string text = "name: textbook-38\npatterns:\n";
  for (const char* pol : {"cross", "parallel"}) {
    for (const auto& [name, formula] : patterns) {
      absl::StrAppend(&text, "  - {name: ", pol, "-", name, ", polarization: ", pol, ", formula: \"", formula, "\"}\n");
    }
  }
  return text;
}

TEST(VerifierTest, FlickerOfTheTotalLightBelowSixtyHertz) {
  auto dir = std::filesystem::temp_directory_path() / ("fastage-flicker-" + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  std::ofstream(dir / "textbook.yaml") << TextbookOrderSet();
  v1::TimingReport report = Verify([](v1::RigConfig* rig) { rig->set_pattern_set("textbook.yaml"); }, dir.string());
  auto v = Of(report, kCheckFlicker);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_WARNING);
  EXPECT_EQ(v[0].device(), "performer");
  EXPECT_EQ(v[0].slot(), -1);
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("modulated by 11."), HasSubstr("at 48 Hz"), HasSubstr("harmonic 2"),
                                    HasSubstr("warning line 1.20 %"), HasSubstr("IEEE 1789")));
  EXPECT_EQ(report.errors(), 0) << Dump(report);

  v1::TimingReport strict = Verify(
      [](v1::RigConfig* rig) {
        rig->set_pattern_set("textbook.yaml");
        rig->mutable_timing()->set_flicker_error_modulation(0.05);
      },
      dir.string());
  std::filesystem::remove_all(dir);
  v = Of(strict, kCheckFlicker);
  ASSERT_EQ(v.size(), 1u) << Dump(strict);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_THAT(v[0].message(), HasSubstr("above the error line 5.00 %"));
}

TEST(VerifierTest, ScheduledSoftwareTriggersWithTooLittleLead) {
  v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    Camera(rig, "mv-02")->mutable_trigger()->set_source(v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE);
    rig->mutable_timing()->set_trigger_lead_slots(1);
  });
  auto v = Of(report, kCheckTriggerLead);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].device(), "mv-02");
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_WARNING);
  EXPECT_THAT(v[0].message(), HasSubstr("sent 1 slot(s) = 1.096 ms ahead"));
  EXPECT_THAT(v[0].fix(), HasSubstr("trigger_lead_slots to >= 2"));
}

}  // namespace
}  // namespace stage::timing

namespace stage::timing {
namespace {

// The shipped rig at `slot_rate_hz` (its frame rates as written: 24 and 912), with exposures and high-speed cameras
// that fit the shorter slot.
v1::TimingReport VerifyAtSlotRate(double slot_rate_hz) {
  return Verify([&](v1::RigConfig* rig) {
    rig->mutable_timing()->set_slot_rate_hz(slot_rate_hz);
    for (v1::CameraConfig& c : *rig->mutable_cameras()) {
      c.set_exposure_us(600);
      if (c.role() == v1::CAMERA_ROLE_HIGH_SPEED) {
        c.set_readout_us(500);
        c.set_max_frame_rate_hz(2000);
      }
    }
  });
}

TEST(VerifierTest, AHintIsOfferedOnlyOnceTheVerifierHasCheckedIt) {
  // At 1140 slots/s the cameras' written frame rates (24, 912) no longer match their triggers (30 Hz, 1140 Hz). A
  // machine-vision divider of round(1140 / 24) = 48 would move its trigger off the full-lit pattern, and a high-speed
  // divider of round(1140 / 912) = 1 is what it has: neither is offered.
  const v1::TimingReport report = VerifyAtSlotRate(1140);
  std::map<std::string, std::string> fixes;
  for (const v1::Violation& v : Of(report, kCheckFrameRate)) fixes[v.device()] = v.fix();
  ASSERT_EQ(fixes.size(), 27u) << Dump(report);
  EXPECT_EQ(fixes["mv-01"], "set cameras[mv-01].frame_rate_hz: 30");
  EXPECT_EQ(fixes["hs-1"], "set cameras[hs-1].frame_rate_hz: 1140");
  EXPECT_EQ(report.errors(), 0) << Dump(report);
}

TEST(VerifierTest, ADividerOffTheCycleMovesTheCameraAcrossPatterns) {
  const v1::TimingReport report = Verify([](v1::RigConfig* rig) {
    Camera(rig, "mv-03")->mutable_trigger()->set_divider(48);
    Camera(rig, "mv-03")->set_frame_rate_hz(19);
  });
  auto v = Of(report, kCheckPatternLock);
  ASSERT_EQ(v.size(), 1u) << Dump(report);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_EQ(v[0].device(), "mv-03");
  EXPECT_EQ(v[0].slot(), 19);
  EXPECT_THAT(v[0].message(), AllOf(HasSubstr("every 48 slots against a cycle of 38 patterns"),
                                    HasSubstr("slot 19 (parallel-full), slot 67 (")));
  EXPECT_THAT(v[0].fix(), HasSubstr("divisor or a multiple of 38 (e.g. 38 or 76)"));
  // The shipped dividers (1 and 38) keep every camera on its patterns.
  EXPECT_TRUE(Of(Verify(), kCheckPatternLock).empty());
}

TEST(VerifierTest, FrameRatesThatAreNotWrittenFollowTheSlotRateAlsoUnderAWhatIf) {
  // The shipped rig without its frame rates: they default to the slot rate over each camera's divider, and a what-if
  // slot rate moves them with it, so no frame-rate warning comes of it.
  std::string text(BuiltinRigText());
  std::string stripped;
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    if (!absl::StrContains(line, " frame_rate_hz:")) absl::StrAppend(&stripped, line, "\n");
  }
  auto rig = LoadRigFromText(stripped, "fastage-without-frame-rates.yaml", ".");
  ASSERT_TRUE(rig.ok()) << rig.status();
  EXPECT_DOUBLE_EQ(rig->rig.cameras(0).frame_rate_hz(), 24);
  auto faster = ApplyRigOverrides(*rig, {"timing.slot_rate_hz=1140", "cameras[*].exposure_us=600",
                                         "cameras[hs-*].readout_us=500", "cameras[hs-*].max_frame_rate_hz=2000"});
  ASSERT_TRUE(faster.ok()) << faster.status();
  for (const v1::CameraConfig& c : faster->rig.cameras()) {
    EXPECT_DOUBLE_EQ(c.frame_rate_hz(), c.role() == v1::CAMERA_ROLE_HIGH_SPEED ? 1140 : 30) << c.id();
  }
  auto report = CheckRigTiming(faster->rig, ".");
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_TRUE(Of(*report, kCheckFrameRate).empty()) << Dump(*report);
}

TEST(VerifierTest, ARigWithoutCamerasOrLightNodesCannotRecordAndSaysWhy) {
  const v1::TimingReport no_cameras = Verify([](v1::RigConfig* rig) { rig->clear_cameras(); });
  auto v = Of(no_cameras, kCheckRig);
  ASSERT_EQ(v.size(), 1u) << Dump(no_cameras);
  EXPECT_EQ(v[0].severity(), v1::SEVERITY_ERROR);
  EXPECT_EQ(v[0].device(), "cameras");
  EXPECT_THAT(v[0].message(), HasSubstr("the rig has no camera: a take would record nothing"));
  const v1::TimingReport no_lights = Verify([](v1::RigConfig* rig) {
    rig->clear_light_nodes();
    rig->mutable_timing()->clear_sync_generator();
  });
  v = Of(no_lights, kCheckRig);
  ASSERT_EQ(v.size(), 1u) << Dump(no_lights);
  EXPECT_EQ(v[0].device(), "light_nodes");
  EXPECT_THAT(v[0].message(), HasSubstr("the rig has no light node: no pattern would be shown"));
  EXPECT_TRUE(Of(Verify(), kCheckRig).empty());
}

}  // namespace
}  // namespace stage::timing
