// Every program, given bad arguments or a bad rig, prints one line naming the problem and exits non-zero; never a
// crash, a hang or a wall of text. --help and --version work everywhere.
#include <filesystem>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;
using ::testing::StartsWith;

constexpr auto kTimeout = std::chrono::seconds(20);

const std::vector<std::string> kPrograms = {"stage-controller", "camera-node", "light-node",   "processing-worker",
                                            "stagectl",         "stage-sim",   "stage-process"};

// One line of stderr, exit code `code`, not killed by a signal, not timed out.
void ExpectOneLineError(const CommandResult& r, int code, const std::string& must_contain) {
  EXPECT_FALSE(r.timed_out);
  EXPECT_EQ(r.exit.signal, 0) << r.exit.Describe();
  EXPECT_EQ(r.exit.exit_code, code) << r.err;
  ASSERT_FALSE(r.err.empty());
  EXPECT_EQ(r.err.back(), '\n');
  EXPECT_EQ(r.err.find('\n'), r.err.size() - 1) << "more than one line:\n" << r.err;
  EXPECT_THAT(r.err, HasSubstr(must_contain));
}

class EveryProgram : public ::testing::TestWithParam<std::string> {};

TEST_P(EveryProgram, HelpAndVersion) {
  CommandResult help = RunCommand({GetParam(), "--help"}, kTimeout);
  EXPECT_EQ(help.exit.exit_code, 0);
  EXPECT_THAT(help.out, HasSubstr("--help"));
  CommandResult version = RunCommand({GetParam(), "--version"}, kTimeout);
  EXPECT_EQ(version.exit.exit_code, 0);
  EXPECT_THAT(version.out, HasSubstr("(FaStage) 0.1.0"));
}

TEST_P(EveryProgram, UnknownFlag) {
  ExpectOneLineError(RunCommand({GetParam(), "--no-such-flag"}, kTimeout), 2, GetParam() + ": error:");
}

INSTANTIATE_TEST_SUITE_P(Cli, EveryProgram, ::testing::ValuesIn(kPrograms), [](const auto& param_info) {
  std::string name = param_info.param;
  for (char& c : name) {
    if (c == '-') c = '_';
  }
  return name;
});

TEST(CliTest, MissingRigFile) {
  for (const std::string program : {"stage-controller", "stage-sim"}) {
    ExpectOneLineError(RunCommand({program, "--config", "/nonexistent/rig.yaml"}, kTimeout), 2,
                       "/nonexistent/rig.yaml: cannot read rig file");
  }
  ExpectOneLineError(RunCommand({"camera-node", "--config", "/nonexistent/rig.yaml", "--id", "mv-01"}, kTimeout), 2,
                     "/nonexistent/rig.yaml: cannot read rig file");
}

TEST(CliTest, BadRigNamesFileLineAndField) {
  TempDir dir;
  std::string rig = dir.Write("bad.yaml",
                              "stage:\n  id: s\ncameras:\n  - id: c\n    role: high-speed\n"
                              "    width: zero\n");
  CommandResult r = RunCommand({"light-node", "--config", rig, "--id", "x"}, kTimeout);
  ExpectOneLineError(r, 2, "bad.yaml:6:12: cameras[0].width: \"zero\" is not an integer >= 0");
  EXPECT_THAT(r.err, StartsWith("light-node: error: "));
}

TEST(CliTest, NodeIdNotInRig) {
  ExpectOneLineError(RunCommand({"camera-node", "--id", "mv-99"}, kTimeout), 2,
                     "camera \"mv-99\" is not in fastage.yaml (built in)");
  ExpectOneLineError(RunCommand({"light-node", "--id", "mv-01"}, kTimeout), 2, "light node \"mv-01\" is not in");
  ExpectOneLineError(RunCommand({"processing-worker", "--id", "w"}, kTimeout), 2, "processing worker \"w\"");
}

TEST(CliTest, RequiredIdMissing) { ExpectOneLineError(RunCommand({"camera-node"}, kTimeout), 2, "--id is required"); }

TEST(CliTest, UnknownBackend) {
  ExpectOneLineError(RunCommand({"light-node", "--id", "lights-gpio-1", "--backend", "dmx"}, kTimeout), 2,
                     "unknown light backend \"dmx\"");
  ExpectOneLineError(RunCommand({"camera-node", "--id", "mv-01", "--backend", "usb"}, kTimeout), 2,
                     "unknown camera backend \"usb\" (sim, aravis)");
}

TEST(CliTest, AnAbsentHardwareCameraFailsLoudly) {
  // The rig says aravis for mv-01 and no such camera is on this machine's networks: without --backend sim the node
  // must refuse, naming the camera, not quietly simulate.
  ExpectOneLineError(RunCommand({"camera-node", "--id", "mv-01"}, kTimeout), 1, "camera \"mv-01\" (");
}

TEST(CliTest, BadListenAddress) {
  ExpectOneLineError(
      RunCommand({"camera-node", "--id", "mv-01", "--backend", "sim", "--listen", "not-an-address"}, kTimeout), 2,
      "listen: \"not-an-address\" is not host:port");
  // Plain text serves loopback only (docs/security.md).
  ExpectOneLineError(
      RunCommand({"camera-node", "--id", "mv-01", "--backend", "sim", "--listen", "192.0.2.1:0"}, kTimeout), 2,
      "will not listen on 192.0.2.1:0 in plain text: plain text is for loopback only");
}

TEST(CliTest, BadLogLevel) {
  ExpectOneLineError(RunCommand({"processing-worker", "--id", "worker-1", "--log-level", "chatty"}, kTimeout), 2,
                     "log level \"chatty\" is not one of");
}

TEST(CliTest, ControllerNeedsAddresses) {
  CommandResult r = RunCommand({"stage-controller"}, kTimeout);
  ExpectOneLineError(r, 2, "cameras[0].address: required by stage-controller");
  EXPECT_THAT(r.err, HasSubstr("more errors)"));
}

TEST(CliTest, StagectlWithoutController) {
  TempDir dir;
  ExpectOneLineError(RunCommand({"stagectl", "--endpoints", dir.path() + "/none.json", "status"}, kTimeout), 2,
                     "no controller address");
  ExpectOneLineError(RunCommand({"stagectl", "--controller", "127.0.0.1:1", "--timeout-ms", "500", "status"}, kTimeout),
                     1, "controller at 127.0.0.1:1");
  std::string garbage = dir.Write("e.json", "{not json");
  ExpectOneLineError(RunCommand({"stagectl", "--endpoints", garbage, "status"}, kTimeout), 2,
                     "not a stage-sim endpoint file");
  ExpectOneLineError(RunCommand({"stagectl"}, kTimeout), 2, "stagectl: error:");
}

// How much ground truth a capture asks for is a word among three, and --no-ground-truth is one of them.
TEST(CliTest, StagectlGroundTruthScopes) {
  ExpectOneLineError(RunCommand({"stagectl", "capture", "--frames", "1", "--ground-truth", "some"}, kTimeout), 2,
                     "--ground-truth: some not in {full,none,scene}");
  ExpectOneLineError(
      RunCommand({"stagectl", "capture", "--frames", "1", "--ground-truth", "full", "--no-ground-truth"}, kTimeout), 2,
      "--ground-truth excludes --no-ground-truth");
  ExpectOneLineError(RunCommand({"stagectl", "calibrate", "--ground-truth", "all"}, kTimeout), 2,
                     "--ground-truth: all not in {full,none,scene}");
}

TEST(CliTest, StageSimBadListen) {
  TempDir dir;
  ExpectOneLineError(RunCommand({"stage-sim", "--run-dir", dir.path(), "--listen", "nowhere"}, kTimeout), 2,
                     "--listen: \"nowhere\" is not host:port");
}

TEST(CliTest, StagectlFindsTheControllerInTheRig) {
  TempDir dir;
  std::string rig = dir.Write("rig.yaml", "stage: {id: s}\ncontroller: {listen: \"127.0.0.1:1\"}\n");
  ExpectOneLineError(RunCommand({"stagectl", "--config", rig, "--timeout-ms", "500", "status"}, kTimeout), 1,
                     "controller at 127.0.0.1:1");
  ExpectOneLineError(RunCommand({"stagectl", "--config", dir.path() + "/none.yaml", "status"}, kTimeout), 2,
                     "none.yaml: cannot read rig file");
}

TEST(CliTest, StageSimBadCommandAndBinDir) {
  TempDir dir;
  ExpectOneLineError(RunCommand({"stage-sim", "--run-dir", dir.path(), "--", "no-such-command-fastage"}, kTimeout), 2,
                     "no-such-command-fastage: not found in PATH");
  ExpectOneLineError(RunCommand({"stage-sim", "--run-dir", dir.path(), "--bin-dir", dir.path()}, kTimeout), 2,
                     "camera-node is missing or not executable");
}

}  // namespace
}  // namespace stage::testing

namespace stage::testing {
namespace {

// A rig that stage-sim runs has no node addresses: the controller's check says so and points to stage-sim's check,
// which passes it (every error of the rig file, the subject and the timing verifier, at once).
TEST(CliTest, ASimulatorRigIsCheckedAsStageSimRunsIt) {
  CommandResult controller = RunCommand({"stage-controller", "--check-config"}, kTimeout);
  EXPECT_EQ(controller.exit.exit_code, 2) << controller.err;
  EXPECT_THAT(controller.err, HasSubstr("cameras[0].address: required by stage-controller"));
  EXPECT_THAT(controller.err, HasSubstr("`stage-sim --check-config --config builtin:fastage`"));
  CommandResult sim = RunCommand({"stage-sim", "--check-config"}, std::chrono::seconds(120));
  EXPECT_EQ(sim.exit.exit_code, 0) << sim.err;
  EXPECT_THAT(sim.out, HasSubstr("ok as stage-sim runs it (27 cameras, 6 light nodes, 1 processing worker)"));
  // With what-ifs, as `stage-sim --set` takes them: a schedule error is exit 3, with the report.
  CommandResult broken =
      RunCommand({"stage-sim", "--check-config", "--set", "cameras[hs-1].exposure_us=1090"}, std::chrono::seconds(120));
  EXPECT_EQ(broken.exit.exit_code, 3) << broken.err;
  EXPECT_THAT(broken.out, HasSubstr("steady-light"));
}

// A rig file with several errors: `stagectl timing check --rig` and `stage-sim --check-config` print every one.
TEST(CliTest, TimingCheckOfARigFilePrintsEveryError) {
  TempDir dir;
  std::string text(ReadFile(std::string(FASTAGE_SOURCE_DIR) + "/common/rigs/fastage.yaml"));
  ASSERT_FALSE(text.empty());
  for (const char* from : {"exposure_us: 900", "slot_rate_hz: 912"}) {
    const size_t at = text.find(from);
    ASSERT_NE(at, std::string::npos) << from;
    text.replace(at, std::string(from).size(), std::string(from).substr(0, std::string(from).find(':')) + ": -1");
  }
  const std::string rig = dir.Write("broken.yaml", text);
  CommandResult check = RunCommand({"stagectl", "timing", "check", "--rig", rig}, kTimeout);
  EXPECT_EQ(check.exit.exit_code, 2) << check.err;
  EXPECT_THAT(check.err, HasSubstr("timing.slot_rate_hz"));
  EXPECT_THAT(check.err, HasSubstr("exposure_us"));
  EXPECT_THAT(check.err, ::testing::Not(HasSubstr("more error")));
  CommandResult sim = RunCommand({"stage-sim", "--check-config", "--config", rig}, kTimeout);
  EXPECT_EQ(sim.exit.exit_code, 2) << sim.err;
  EXPECT_THAT(sim.err, HasSubstr("timing.slot_rate_hz"));
  EXPECT_THAT(sim.err, HasSubstr("exposure_us"));
}

TEST(CliTest, TheMessageWithoutAStageSaysItsAdviceOnce) {
  TempDir dir;
  CommandResult r = RunCommand({"stagectl", "--endpoints", dir.path() + "/none.json", "status"}, kTimeout);
  ExpectOneLineError(r, 2,
                     "no controller address: pass --controller HOST:PORT or --config RIG, or start stage-sim "
                     "(no stage-sim endpoint file at ");
  EXPECT_EQ(r.err.find("start stage-sim"), r.err.rfind("start stage-sim")) << r.err;
}

}  // namespace
}  // namespace stage::testing

namespace stage::testing {
namespace {

// stage-sim-render on a rig without hs-2: it renders the rig's first high-speed camera, not a camera it lacks.
TEST(CliTest, StageSimRenderTakesTheRigsFirstHighSpeedCamera) {
  TempDir dir;
  std::string text = ReadFile(std::string(FASTAGE_SOURCE_DIR) + "/common/rigs/fastage.yaml");
  for (const std::string from : {"id: hs-1", "id: hs-2", "id: hs-3"}) {
    const size_t at = text.find(from);
    ASSERT_NE(at, std::string::npos) << from;
    text.replace(at, from.size(), "id: fast-" + from.substr(from.size() - 1));
  }
  const std::string rig = dir.Write("no-hs-2.yaml", text);
  CommandResult r = RunCommand({"stage-sim-render", "--config", rig, "--set", "sim.render_scale=0.01", "--out",
                                dir.path() + "/sheet.png", "--json"},
                               std::chrono::seconds(120));
  ASSERT_EQ(r.exit.exit_code, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("\"camera\": \"fast-1\""));
}

// A take refused for its flags writes nothing: --range-of-motion-s's performance file is written only after the
// flags are checked (a --take with --ground-truth, --take-cameras without --take, bad or empty --frames).
TEST(CliTest, StageSimRenderRefusesBadFlagsBeforeWritingTheRangeOfMotion) {
  TempDir dir;
  const std::string take = dir.path() + "/take";
  const std::vector<std::pair<std::vector<std::string>, std::string>> refused = {
      {{"--take", take, "--ground-truth", dir.path() + "/truth"}, "it takes no --ground-truth"},
      {{"--take", take, "--frames", "a:b"}, "--frames \"a:b\" is not A:B"},
      {{"--take", take, "--frames", "5:2"}, "--frames \"5:2\" holds no frame"},
      {{"--take-cameras", "mv-01", "--ground-truth", take}, "need --take"}};
  for (const auto& [flags, message] : refused) {
    std::vector<std::string> args = {"stage-sim-render", "--range-of-motion-s", "60"};
    args.insert(args.end(), flags.begin(), flags.end());
    ExpectOneLineError(RunCommand(args, kTimeout), 2, message);
    EXPECT_FALSE(std::filesystem::exists(take + "/range-of-motion.yaml")) << message;
  }
}

}  // namespace
}  // namespace stage::testing
