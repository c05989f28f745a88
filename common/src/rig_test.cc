// Rig loading: the shipped rig, defaults, and the error message for each kind of bad input (file, line, field).
#include "stage/common/rig.h"

#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_replace.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using ::testing::StartsWith;

// A small valid rig; tests break one thing at a time.
constexpr const char* kGoodRig = R"(stage:
  id: test-stage
  name: Test stage
timing:
  sync_generator: gpio-a
cameras:
  - id: cam-a
    role: machine-vision
    width: 640
    height: 480
    exposure_us: 500
    intrinsics: {focal_length_mm: 35, pixel_size_um: 4.8}
    pose: {position_mm: [0, 0, 1000]}
  - id: cam-b
    role: high-speed
    width: 1024
    height: 512
    exposure_us: 800
    ram_gib: 64
    intrinsics: {focal_length_mm: 85, pixel_size_um: 6.75}
    pose: {position_mm: [300, 0, 1000]}
light_nodes:
  - id: gpio-a
    backend: gpiod
    channel_count: 4
    gpiod: {chip: gpiochip0, channel_lines: [0, 1, 2, 3], slot_clock_line: 4, drives_slot_clock: true}
    unit_limits: {max_current_ma: 700}
    units:
      - {id: led-1, direction: [0, 0, 1], parallel_channel: 0, cross_channel: 1}
      - {id: led-2, direction: [0, 1, 0], parallel_channel: 2, cross_channel: 3}
  - id: board-a
    backend: modbus
    channel_count: 2
    modbus: {tcp: {host: board-a.local}}
    unit_limits: {max_current_ma: 500}
    units:
      - {id: led-3, direction: [1, 0, 0], parallel_channel: 0, cross_channel: 1}
processing_workers:
  - id: worker-1
)";

class TempDir {
 public:
  TempDir() {
    char tmpl[] = "/tmp/fastage-rig-test.XXXXXX";
    path_ = mkdtemp(tmpl);
  }
  ~TempDir() { std::filesystem::remove_all(path_); }
  std::string Write(const std::string& name, const std::string& text) const {
    std::string p = path_ + "/" + name;
    std::ofstream(p) << text;
    return p;
  }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

// Loads `text` as the file "rig.yaml" in a temporary directory and returns the error message ("" if it loaded).
std::string LoadError(const std::string& text, const RigValidationOptions& options = {}) {
  TempDir dir;
  auto loaded = LoadRig(dir.Write("rig.yaml", text), options);
  if (loaded.ok()) return "";
  std::string message(loaded.status().message());
  // Tests assert the file name as users see it: strip the temporary directory.
  return absl::StrReplaceAll(message, {{dir.path() + "/", ""}});
}

std::string Replace(const std::string& from, const std::string& to) {
  std::string text = kGoodRig;
  EXPECT_NE(text.find(from), std::string::npos) << from;
  return absl::StrReplaceAll(text, {{from, to}});
}

TEST(RigTest, GoodRigLoadsWithDefaults) {
  EXPECT_EQ(LoadError(kGoodRig), "");
  TempDir dir;
  auto loaded = LoadRig(dir.Write("rig.yaml", kGoodRig));
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  const auto& rig = loaded->rig;
  EXPECT_EQ(rig.controller().health_poll_interval_ms(), 200u);
  EXPECT_EQ(rig.timing().slot_rate_hz(), 912);
  EXPECT_EQ(rig.pattern_set(), "fastage-38");
  // Role-dependent defaults: MV cameras on the parallel full-on slot of 38, HS cameras every slot.
  EXPECT_EQ(rig.cameras(0).frame_rate_hz(), 24);
  EXPECT_EQ(rig.cameras(0).trigger().divider(), 38u);
  EXPECT_EQ(rig.cameras(0).trigger().slot_phase(), 19u);
  EXPECT_EQ(rig.cameras(1).frame_rate_hz(), 912);
  EXPECT_EQ(rig.cameras(1).trigger().divider(), 1u);
  EXPECT_EQ(rig.cameras(0).backend(), v1::CAMERA_BACKEND_SIM);
  EXPECT_EQ(rig.cameras(0).pixel_format(), v1::PIXEL_FORMAT_BAYER_RG8);
  EXPECT_EQ(rig.light_nodes(1).modbus().tcp().port(), 502u);
  EXPECT_EQ(rig.light_nodes(0).unit_limits().max_duty_cycle(), 0.5);
  EXPECT_EQ(rig.light_nodes(0).units(0).intensity_scale(), 1.0);
}

TEST(RigTest, ShippedRigIsTheFaStage) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  const auto& rig = loaded->rig;
  int mv = 0, hs = 0;
  for (const auto& c : rig.cameras()) {
    if (c.role() == v1::CAMERA_ROLE_MACHINE_VISION) {
      ++mv;
      EXPECT_EQ(c.width(), 2592u);
      EXPECT_EQ(c.height(), 2048u);
      EXPECT_EQ(c.frame_rate_hz(), 24);
      EXPECT_EQ(c.pixel_format(), v1::PIXEL_FORMAT_BAYER_RG8);
    } else {
      ++hs;
      EXPECT_EQ(c.width(), 4096u);
      EXPECT_EQ(c.height(), 2304u);
      EXPECT_EQ(c.frame_rate_hz(), 912);
    }
  }
  EXPECT_EQ(mv, 24);
  EXPECT_EQ(hs, 3);
  int units = 0;
  bool modbus = false, gpiod = false;
  for (const auto& n : rig.light_nodes()) {
    units += n.units_size();
    modbus = modbus || n.backend() == v1::LIGHT_BACKEND_MODBUS;
    gpiod = gpiod || n.backend() == v1::LIGHT_BACKEND_GPIOD;
    for (const auto& u : n.units()) {
      EXPECT_TRUE(u.has_parallel_channel() && u.has_cross_channel()) << u.id();
      // A semi-dome around the face: no unit far behind the head.
      EXPECT_GT(u.direction().z(), -0.31) << u.id();
    }
  }
  EXPECT_GE(units, 120);
  EXPECT_TRUE(modbus && gpiod);
  EXPECT_EQ(rig.pattern_set(), "fastage-38");
}

TEST(RigTest, JsonRigLoadsToo) {
  // stage-sim hands the controller a JSON rig: YAML is a superset of JSON, and enum names may be the full ones.
  std::string json = R"({"stage": {"id": "j"}, "cameras": [{"id": "c", "role": "CAMERA_ROLE_HIGH_SPEED",
    "width": 8, "height": 8, "exposure_us": 100, "ram_gib": 1, "address": "127.0.0.1:5000",
    "intrinsics": {"focal_length_mm": 35, "pixel_size_um": 5}, "pose": {"position_mm": {"x": 0, "y": 0, "z": 500}}}]})";
  TempDir dir;
  auto loaded = LoadRig(dir.Write("rig.json", json), {.require_addresses = true});
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(loaded->rig.cameras(0).role(), v1::CAMERA_ROLE_HIGH_SPEED);
}

// --- One test per kind of bad input. Each asserts the file, the line where known, and the field path. ---

TEST(RigErrorTest, UnknownFieldSuggestsTheRightOne) {
  EXPECT_THAT(LoadError(Replace("    exposure_us: 500", "    exposure_usec: 500")),
              AllOf(StartsWith("rig.yaml:11:5: cameras[0].exposure_usec: unknown field"),
                    HasSubstr("did you mean \"exposure_us\"")));
}

TEST(RigErrorTest, UnknownTopLevelFieldListsValidFields) {
  EXPECT_THAT(LoadError(std::string(kGoodRig) + "zzzzz: 1\n"),
              AllOf(StartsWith("rig.yaml:"), HasSubstr("zzzzz: unknown field"), HasSubstr("valid fields: stage")));
}

TEST(RigErrorTest, WrongScalarType) {
  EXPECT_THAT(LoadError(Replace("    width: 640", "    width: wide")),
              StartsWith("rig.yaml:9:12: cameras[0].width: \"wide\" is not an integer >= 0"));
}

TEST(RigErrorTest, FractionForAnInteger) {
  EXPECT_THAT(LoadError(Replace("    width: 640", "    width: 640.5")),
              AllOf(StartsWith("rig.yaml:9:12: cameras[0].width:"), HasSubstr("has a fraction")));
}

TEST(RigErrorTest, NegativeForUnsigned) {
  EXPECT_THAT(LoadError(Replace("    height: 480", "    height: -480")),
              StartsWith("rig.yaml:10:13: cameras[0].height: -480 is negative"));
}

TEST(RigErrorTest, MapWhereListExpected) {
  EXPECT_THAT(LoadError(Replace("processing_workers:\n  - id: worker-1", "processing_workers:\n  id: worker-1")),
              AllOf(StartsWith("rig.yaml:"), HasSubstr("processing_workers: expected a list, got a map")));
}

TEST(RigErrorTest, MissingRequiredField) {
  EXPECT_THAT(LoadError(Replace("    exposure_us: 500\n", "")),
              StartsWith("rig.yaml:7:5: cameras[0].exposure_us: required field is missing"));
}

TEST(RigErrorTest, MissingStageId) {
  EXPECT_THAT(LoadError(Replace("  id: test-stage\n", "")),
              StartsWith("rig.yaml:1:1: stage.id: required field is missing"));
}

TEST(RigErrorTest, MutualTlsNeedsItsFilesAndPlainTextTakesNone) {
  EXPECT_THAT(LoadError(kGoodRig + std::string("security: {transport: mutual-tls, cert_dir: pki}\n")),
              HasSubstr("security.ca_file: mutual TLS needs it"));
  EXPECT_THAT(LoadError(kGoodRig + std::string("security: {cert_dir: pki}\n")),
              HasSubstr("security.transport: ca_file and cert_dir are set, but the transport is plain text"));
  EXPECT_THAT(LoadError(kGoodRig + std::string("security: {reload_interval_s: 0}\n")),
              HasSubstr("security.reload_interval_s"));
  EXPECT_EQ(LoadError(kGoodRig + std::string("security: {transport: mutual-tls, ca_file: pki/ca.crt, cert_dir: "
                                             "pki}\n")),
            "");
}

TEST(RigErrorTest, OutOfRangeValue) {
  EXPECT_THAT(LoadError(Replace("    exposure_us: 500", "    exposure_us: 0")),
              StartsWith("rig.yaml:11:5: cameras[0].exposure_us: 0 is not > 0"));
}

TEST(RigErrorTest, ExposureLongerThanFramePeriod) {
  EXPECT_THAT(LoadError(Replace("    exposure_us: 800", "    exposure_us: 1200")),
              AllOf(StartsWith("rig.yaml:18:5: cameras[1].exposure_us:"),
                    HasSubstr("not shorter than the frame period 1096.491 us at 912 fps")));
}

TEST(RigErrorTest, DuplicateNodeIds) {
  EXPECT_THAT(
      LoadError(Replace("  - id: cam-b", "  - id: cam-a")),
      AllOf(StartsWith("rig.yaml:14:5: cameras[1].id: duplicate node id \"cam-a\""), HasSubstr("also cameras[0].id")));
}

TEST(RigErrorTest, DuplicateIdsAcrossKinds) {
  EXPECT_THAT(
      LoadError(Replace("  - id: worker-1", "  - id: board-a")),
      AllOf(HasSubstr("processing_workers[0].id: duplicate node id \"board-a\""), HasSubstr("also light_nodes[1].id")));
}

TEST(RigErrorTest, DuplicateLedUnitIds) {
  EXPECT_THAT(LoadError(Replace("{id: led-3,", "{id: led-1,")),
              AllOf(StartsWith("rig.yaml:37:"), HasSubstr("light_nodes[1].units[0].id: duplicate LED unit id")));
}

TEST(RigErrorTest, ReferencedNodeNotDefined) {
  EXPECT_THAT(LoadError(Replace("  sync_generator: gpio-a", "  sync_generator: gpio-z")),
              AllOf(StartsWith("rig.yaml:5:3: timing.sync_generator: light node \"gpio-z\" is not defined"),
                    HasSubstr("light nodes: gpio-a, board-a")));
}

TEST(RigErrorTest, ReferencedNodeOfWrongKind) {
  EXPECT_THAT(LoadError(Replace("  sync_generator: gpio-a", "  sync_generator: board-a")),
              HasSubstr("timing.sync_generator: light node \"board-a\" cannot generate the slot clock"));
}

TEST(RigErrorTest, ClockWitnessOnlyForAnExternalGeneratorAndNotOnAModbusBoard) {
  EXPECT_THAT(LoadError(Replace("  sync_generator: gpio-a", "  sync_generator: gpio-a\n  clock_witness: gpio-a")),
              HasSubstr("timing.clock_witness: is set, but timing.sync_generator (\"gpio-a\") drives the clock"));
  const std::string external = absl::StrReplaceAll(
      kGoodRig, {{"  sync_generator: gpio-a", "  clock_witness: board-a"}, {", drives_slot_clock: true", ""}});
  EXPECT_THAT(LoadError(external),
              HasSubstr("timing.clock_witness: light node \"board-a\" cannot timestamp the slot clock"));
  EXPECT_EQ(LoadError(absl::StrReplaceAll(external, {{"clock_witness: board-a", "clock_witness: gpio-a"}})), "");
  EXPECT_THAT(LoadError(absl::StrReplaceAll(external, {{"clock_witness: board-a", "clock_witness: gpio-z"}})),
              HasSubstr("timing.clock_witness: light node \"gpio-z\" is not defined"));
}

TEST(RigErrorTest, UnreadableFile) {
  auto loaded = LoadRig("/nonexistent/dir/rig.yaml");
  ASSERT_FALSE(loaded.ok());
  EXPECT_THAT(std::string(loaded.status().message()),
              AllOf(StartsWith("/nonexistent/dir/rig.yaml: cannot read rig file"), HasSubstr("No such file")));
}

TEST(RigErrorTest, FileWithoutReadPermission) {
  if (geteuid() == 0) GTEST_SKIP() << "root reads any file; permission errors cannot be provoked";
  TempDir dir;
  std::string path = dir.Write("rig.yaml", kGoodRig);
  chmod(path.c_str(), 0);
  auto loaded = LoadRig(path);
  ASSERT_FALSE(loaded.ok());
  EXPECT_THAT(std::string(loaded.status().message()), HasSubstr("Permission denied"));
}

TEST(RigErrorTest, DirectoryInsteadOfFile) {
  TempDir dir;
  auto loaded = LoadRig(dir.path());
  ASSERT_FALSE(loaded.ok());
  EXPECT_THAT(std::string(loaded.status().message()), HasSubstr("is a directory"));
}

TEST(RigErrorTest, YamlSyntaxError) {
  EXPECT_THAT(LoadError(Replace("    width: 640", "    width: [640")),
              AllOf(StartsWith("rig.yaml:"), HasSubstr("YAML syntax error")));
}

TEST(RigErrorTest, EmptyFile) { EXPECT_THAT(LoadError(""), StartsWith("rig.yaml: the file is empty")); }

TEST(RigErrorTest, BadEnumValueListsValidOnes) {
  EXPECT_THAT(LoadError(Replace("role: machine-vision", "role: webcam")),
              AllOf(StartsWith("rig.yaml:8:11: cameras[0].role: \"webcam\" is not a valid CameraRole"),
                    HasSubstr("valid values: machine-vision, high-speed")));
}

TEST(RigErrorTest, TwoMembersOfOneOneof) {
  EXPECT_THAT(LoadError(Replace("    modbus: {tcp: {host: board-a.local}}",
                                "    modbus: {tcp: {host: board-a.local}}\n    sim: {}")),
              AllOf(HasSubstr("light_nodes[1].sim: only one of sim, gpiod, modbus may be set"),
                    HasSubstr("modbus is set already")));
}

TEST(RigErrorTest, BackendSettingsMissing) {
  EXPECT_THAT(LoadError(Replace("    modbus: {tcp: {host: board-a.local}}\n", "")),
              HasSubstr("light_nodes[1].modbus: required for backend modbus"));
}

TEST(RigErrorTest, GpiodLinesMustFitTheChannels) {
  const std::string lines = "channel_lines: [0, 1, 2, 3], slot_clock_line: 4";
  EXPECT_THAT(LoadError(Replace(lines, "channel_lines: [0, 1, 2, 3], lines_per_channel: 2, slot_clock_line: 9")),
              HasSubstr("light_nodes[0].gpiod.channel_lines: has 4 lines; channel_count x lines_per_channel is 8"));
  EXPECT_THAT(LoadError(Replace(lines, "channel_lines: [0, 1, 2, 2], slot_clock_line: 4")),
              HasSubstr("light_nodes[0].gpiod.channel_lines: lists a line twice"));
  EXPECT_THAT(LoadError(Replace(lines, "channel_lines: [0, 1, 2, 3], slot_clock_line: 3")),
              HasSubstr("light_nodes[0].gpiod.slot_clock_line: line 3 is also a channel line"));
  EXPECT_THAT(LoadError(Replace(lines, "channel_lines: [0, 1, 2, 3]")),
              HasSubstr("light_nodes[0].gpiod.slot_clock_line: required for backend gpiod"));
}

TEST(RigErrorTest, BoardSilenceNeedsAFakeModbusBoard) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  const std::vector<std::string> fault = {"sim.faults[0].target=lights-modbus-2", "sim.faults[0].board_silent_at_s=1",
                                          "sim.faults[0].board_silent_s=2"};
  auto without_fakes = ApplyRigOverrides(*rig, fault);
  ASSERT_FALSE(without_fakes.ok());
  EXPECT_THAT(std::string(without_fakes.status().message()),
              HasSubstr("sim.faults[0]: board_silent applies to a fake LED board (sim.modbus_fakes"));
  std::vector<std::string> with_fakes = fault;
  with_fakes.push_back("sim.modbus_fakes=true");
  EXPECT_TRUE(ApplyRigOverrides(*rig, with_fakes).ok());
  with_fakes[0] = "sim.faults[0].target=lights-gpio-1";
  EXPECT_FALSE(ApplyRigOverrides(*rig, with_fakes).ok()) << "a gpiod node has no board";
}

TEST(RigTest, TextureSamplesDefaultToTheLightingsButFourOnTheBoard) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  auto head = ApplyRigOverrides(*rig, {"sim.supersample=2"});
  ASSERT_TRUE(head.ok()) << head.status();
  EXPECT_EQ(head->rig.sim().texture_samples(), 2u);
  auto board = ApplyRigOverrides(*rig, {"sim.subject.kind=charuco"});
  ASSERT_TRUE(board.ok()) << board.status();
  EXPECT_EQ(board->rig.sim().texture_samples(), 4u);
  auto coarser = ApplyRigOverrides(*rig, {"sim.supersample=3", "sim.texture_samples=2"});
  ASSERT_FALSE(coarser.ok());
  EXPECT_THAT(std::string(coarser.status().message()), HasSubstr("sim.texture_samples"));
}

TEST(RigTest, AnIdentityIsAProceduralHeadsOnly) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  auto performer = ApplyRigOverrides(*rig, {"sim.subject.identity=5"});
  ASSERT_TRUE(performer.ok()) << performer.status();
  EXPECT_EQ(performer->rig.sim().subject().identity(), 5u);
  auto sphere = ApplyRigOverrides(*rig, {"sim.subject.kind=sphere", "sim.subject.identity=5"});
  ASSERT_FALSE(sphere.ok());
  EXPECT_THAT(std::string(sphere.status().message()),
              HasSubstr("sim.subject.identity: draws the procedural head's proportions"));
}

TEST(RigErrorTest, ChannelOutOfRange) {
  EXPECT_THAT(LoadError(Replace("parallel_channel: 2, cross_channel: 3", "parallel_channel: 2, cross_channel: 4")),
              AllOf(StartsWith("rig.yaml:30:64:"),
                    HasSubstr("light_nodes[0].units[1].cross_channel: 4 is not < channel_count 4")));
}

TEST(RigErrorTest, ChannelUsedTwice) {
  EXPECT_THAT(LoadError(Replace("parallel_channel: 2, cross_channel: 3", "parallel_channel: 1, cross_channel: 3")),
              HasSubstr("light_nodes[0].units[1].parallel_channel: channel 1 is already used by "
                        "light_nodes[0].units[0].cross_channel"));
}

TEST(RigErrorTest, DirectionNotUnitVector) {
  EXPECT_THAT(LoadError(Replace("direction: [0, 1, 0]", "direction: [0, 2, 0]")),
              HasSubstr("light_nodes[0].units[1].direction: is not a unit vector (length 2.0000)"));
}

TEST(RigErrorTest, VectorOfWrongLength) {
  EXPECT_THAT(LoadError(Replace("direction: [0, 1, 0]", "direction: [0, 1]")),
              HasSubstr("light_nodes[0].units[1].direction: expected a list of 3 numbers [x, y, z], got 2"));
}

TEST(RigErrorTest, DuplicateYamlKey) {
  EXPECT_THAT(LoadError(Replace("    width: 640", "    width: 640\n    width: 800")),
              StartsWith("rig.yaml:10:5: cameras[0].width: duplicate key"));
}

TEST(RigErrorTest, PatternSetFileMissing) {
  EXPECT_THAT(LoadError(std::string(kGoodRig) + "pattern_set: my-patterns.yaml\n"),
              AllOf(HasSubstr("pattern_set: \"my-patterns.yaml\" is neither a built-in pattern set"),
                    HasSubstr("my-patterns.yaml)")));
}

TEST(RigErrorTest, AddressesRequiredByTheController) {
  EXPECT_THAT(LoadError(kGoodRig, {.require_addresses = true}),
              AllOf(StartsWith("rig.yaml:7:5: cameras[0].address: required by stage-controller"),
                    HasSubstr("(and 4 more errors)")));
}

TEST(RigErrorTest, BadAddress) {
  EXPECT_THAT(LoadError(Replace("  - id: worker-1", "  - id: worker-1\n    address: localhost")),
              HasSubstr("processing_workers[0].address: \"localhost\" is not host:port"));
}

TEST(RigErrorTest, AllErrorsAreListed) {
  std::vector<std::string> errors;
  TempDir dir;
  std::string text =
      absl::StrReplaceAll(kGoodRig, {{"exposure_us: 500", "exposure_us: 0"}, {"  id: test-stage\n", ""}});
  auto loaded = LoadRig(dir.Write("rig.yaml", text), {}, &errors);
  ASSERT_FALSE(loaded.ok());
  ASSERT_EQ(errors.size(), 2u);
  EXPECT_THAT(errors[0], HasSubstr("stage.id"));
  EXPECT_THAT(errors[1], HasSubstr("cameras[0].exposure_us"));
  EXPECT_THAT(std::string(loaded.status().message()), HasSubstr("(and 1 more errors)"));
}

TEST(RigTest, HashIsStableAndIgnoresAddresses) {
  auto a = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(a.ok());
  v1::RigConfig b = a->rig;
  EXPECT_EQ(RigHash(a->rig), RigHash(b));
  b.mutable_cameras(0)->set_address("127.0.0.1:1234");
  EXPECT_EQ(RigHash(a->rig), RigHash(b));
  b.mutable_cameras(0)->set_exposure_us(901);
  EXPECT_NE(RigHash(a->rig), RigHash(b));
  EXPECT_EQ(RigHash(a->rig).size(), 16u);
}

TEST(RigTest, FindNodeNamesTheValidIds) {
  TempDir dir;
  auto loaded = LoadRig(dir.Write("rig.yaml", kGoodRig));
  ASSERT_TRUE(loaded.ok());
  EXPECT_TRUE(FindCamera(*loaded, "cam-b").ok());
  auto missing = FindLightNode(*loaded, "nope");
  ASSERT_FALSE(missing.ok());
  EXPECT_THAT(std::string(missing.status().message()),
              AllOf(HasSubstr("light node \"nope\" is not in"), HasSubstr("(light nodes: gpio-a, board-a)")));
}

TEST(HostPortTest, Parses) {
  std::string host;
  int port;
  ASSERT_TRUE(ParseHostPort("127.0.0.1:80", &host, &port).ok());
  EXPECT_EQ(host, "127.0.0.1");
  EXPECT_EQ(port, 80);
  ASSERT_TRUE(ParseHostPort("[::1]:0", &host, &port).ok());
  EXPECT_EQ(host, "::1");
  EXPECT_FALSE(ParseHostPort("host", &host, &port).ok());
  EXPECT_FALSE(ParseHostPort("host:70000", &host, &port).ok());
  EXPECT_FALSE(ParseHostPort("::1:80", &host, &port).ok());
}

}  // namespace
}  // namespace stage
