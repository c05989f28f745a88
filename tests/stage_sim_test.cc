// The full FaStage rig under stage-sim, as a user runs it: every node up in `stagectl status --json`; a camera node
// killed with SIGKILL is reported down within 1 s while the rest stay up; stopping the stage leaves no process, even
// one that hangs (SIGSTOP) and ignores SIGTERM.
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <sys/stat.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <thread>

#include "absl/strings/str_format.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/clock.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/timing/pattern_set.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "stage/v1/sim.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using StageSimTest = SimulatedStageTest;

TEST_F(StageSimTest, FullRigComesUpReportsAKilledCameraAndGoesDownClean) {
  ASSERT_NO_FATAL_FAILURE(StartStage());
  ASSERT_GT(pids_.size(), 30u);

  // 1. Every node up, as stagectl reports it to scripts.
  nlohmann::json status = StatusJson();
  int cameras = 0, lights = 0, workers = 0;
  for (const auto& node : status["nodes"]) {
    EXPECT_EQ(node["state"], "NODE_STATE_UP") << node.dump();
    if (node["kind"] == "NODE_KIND_CAMERA") ++cameras;
    if (node["kind"] == "NODE_KIND_LIGHT") ++lights;
    if (node["kind"] == "NODE_KIND_PROCESSING_WORKER") ++workers;
  }
  EXPECT_EQ(cameras, 27);
  EXPECT_EQ(lights, 6);
  EXPECT_EQ(workers, 1);
  EXPECT_EQ(status["nodes_up"], status["nodes_total"]);
  // The controller compiled and verified the live rig's schedule.
  EXPECT_EQ(status["timing_errors"], 0);
  EXPECT_EQ(status["schedule_hash"].get<std::string>().size(), 16u);

  // The live rig's timing, what-if included, through the controller.
  CommandResult check = RunCommand({"stagectl", "--endpoints", run_dir_.path() + "/endpoints.json", "timing", "check",
                                    "--set", "cameras[hs-2].exposure_us=1050"},
                                   std::chrono::seconds(20));
  EXPECT_EQ(check.exit.exit_code, 3) << check.err;
  EXPECT_THAT(check.out, ::testing::HasSubstr("the live rig of the controller at " + endpoints_.controller()));
  EXPECT_THAT(check.out, ::testing::HasSubstr("steady-light    hs-2 slot 0"));
  // The shipped rig triggers by hardware line: no scheduled triggers to rehearse.
  CommandResult rehearse = RunCommand(
      {"stagectl", "--endpoints", run_dir_.path() + "/endpoints.json", "timing", "rehearse"}, std::chrono::seconds(20));
  EXPECT_EQ(rehearse.exit.exit_code, 2) << rehearse.err;
  EXPECT_THAT(rehearse.err, ::testing::HasSubstr("no camera of the rig uses trigger.source scheduled-software"));

  // 2. SIGKILL one camera node (by pid, from the endpoint file).
  pid_t victim = 0;
  for (const auto& p : endpoints_.processes()) {
    if (p.id() == "mv-07") victim = p.pid();
  }
  ASSERT_GT(victim, 0);
  auto stub = v1::StageController::NewStub(MakeChannel(endpoints_.controller()));
  int64_t killed_at = UnixNowNs();
  ASSERT_EQ(kill(victim, SIGKILL), 0);
  v1::StageStatus seen;
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  bool down = false;
  while (!down && std::chrono::steady_clock::now() < deadline) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
    ASSERT_TRUE(stub->GetStageStatus(&context, v1::GetStageStatusRequest(), &seen).ok());
    for (const auto& n : seen.nodes()) {
      if (n.id() == "mv-07" && n.state() == v1::NODE_STATE_DOWN) down = true;
    }
    if (!down) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  ASSERT_TRUE(down) << "mv-07 was never reported down";
  for (const auto& n : seen.nodes()) {
    if (n.id() == "mv-07") {
      // The controller's own record of when it saw the change: within 1 s of the kill.
      EXPECT_LT(n.state_since_unix_ns() - killed_at, 1'000'000'000)
          << "detected after " << (n.state_since_unix_ns() - killed_at) / 1e6 << " ms";
      EXPECT_FALSE(n.reason().empty());
    } else {
      EXPECT_EQ(n.state(), v1::NODE_STATE_UP) << n.id() << ": " << n.reason();
    }
  }
  // stagectl agrees, and says so in its exit code (3: not every node up).
  CommandResult table =
      RunCommand({"stagectl", "--endpoints", run_dir_.path() + "/endpoints.json", "status"}, std::chrono::seconds(20));
  EXPECT_EQ(table.exit.exit_code, 3);
  EXPECT_THAT(table.out, ::testing::HasSubstr("33 of 34 nodes up"));

  // 3. Hang one light node (SIGSTOP: it cannot act on SIGTERM), then stop the stage.
  pid_t hung = 0;
  for (const auto& p : endpoints_.processes()) {
    if (p.id() == "lights-modbus-2") hung = p.pid();
  }
  ASSERT_EQ(kill(hung, SIGSTOP), 0);
  sim_->Signal(SIGTERM);
  auto exit = sim_->Wait(std::chrono::seconds(30));
  ASSERT_TRUE(exit.has_value()) << "stage-sim did not stop";
  EXPECT_EQ(exit->exit_code, 0) << ReadFile(run_dir_.path() + "/stage-sim.log");
  for (const auto& p : endpoints_.processes()) EXPECT_FALSE(Alive(p.pid())) << p.id() << " (pid " << p.pid() << ")";
  std::string log = ReadFile(run_dir_.path() + "/stage-sim.log");
  EXPECT_THAT(log, ::testing::HasSubstr("camera-node mv-07"));  // the killed child was reported
  EXPECT_THAT(log, ::testing::HasSubstr("lights-modbus-2"));    // and the hung one escalated to SIGKILL
  EXPECT_FALSE(std::filesystem::exists(run_dir_.path() + "/endpoints.json"));
}

TEST_F(StageSimTest, KilledSupervisorTakesItsChildrenWithIt) {
  ASSERT_NO_FATAL_FAILURE(StartStage());
  ASSERT_EQ(kill(sim_->pid(), SIGKILL), 0);
  sim_->Wait();
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  for (pid_t pid : pids_) {
    while (Alive(pid) && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    EXPECT_FALSE(Alive(pid)) << "pid " << pid << " outlived stage-sim";
  }
}

TEST_F(StageSimTest, CommandModeRunsTheCommandAndReturnsItsExitCode) {
  CommandResult r = RunCommand({"stage-sim", "--run-dir", run_dir_.path(), "--", BinDir() + "/stagectl", "status"},
                               std::chrono::seconds(120));
  ASSERT_FALSE(r.timed_out);
  EXPECT_EQ(r.exit.exit_code, 0) << r.err;
  EXPECT_THAT(r.out, ::testing::HasSubstr("34 of 34 nodes up"));
  EXPECT_THAT(r.err, ::testing::HasSubstr("stage-sim: stage down"));
  CommandResult fails =
      RunCommand({"stage-sim", "--run-dir", run_dir_.path(), "--", "sh", "-c", "exit 7"}, std::chrono::seconds(120));
  EXPECT_EQ(fails.exit.exit_code, 7);
}

TEST_F(StageSimTest, SecondStageSimOnTheSameRunDirIsRefused) {
  ASSERT_NO_FATAL_FAILURE(StartStage());
  CommandResult r = RunCommand({"stage-sim", "--run-dir", run_dir_.path()}, std::chrono::seconds(30));
  EXPECT_EQ(r.exit.exit_code, 2);
  EXPECT_THAT(r.err, ::testing::HasSubstr("another stage-sim (pid " + std::to_string(sim_->pid()) + ")"));
}

// Scheduled software triggers rehearsed on the live stage: the controller streams them to the camera nodes of the
// cameras that use them, converted with its clock measurements; every trigger is accounted for.
TEST_F(StageSimTest, TriggerRehearsalThroughTheController) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(
      *loaded, {"cameras[hs-*].trigger.source=scheduled-software", "cameras[*].width=64", "cameras[*].height=32"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  // A pattern-set file beside the rig file: stage-sim's effective rig (in its run directory) must still find it.
  TempDir rig_dir;
  std::string patterns(timing::BuiltinFastage38Text());
  patterns.replace(patterns.find("name: fastage-38"), 16, "name: fastage-38-copy");
  rig_dir.Write("patterns.yaml", patterns);
  rig->rig.set_pattern_set("patterns.yaml");
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  ASSERT_TRUE(google::protobuf::util::MessageToJsonString(rig->rig, &json, print).ok());
  ASSERT_NO_FATAL_FAILURE(StartStage({"--config", rig_dir.Write("rig.json", json)}));
  CommandResult show = RunCommand({"stagectl", "--endpoints", run_dir_.path() + "/endpoints.json", "timing", "show"},
                                  std::chrono::seconds(20));
  EXPECT_EQ(show.exit.exit_code, 0) << show.err;
  EXPECT_THAT(show.out, ::testing::HasSubstr("pattern set fastage-38-copy: 38 patterns"));
  CommandResult r = RunCommand({"stagectl", "--endpoints", run_dir_.path() + "/endpoints.json", "timing", "rehearse",
                                "--slots", "300", "--json"},
                               std::chrono::seconds(60));
  ASSERT_TRUE(r.exit.exit_code == 0 || r.exit.exit_code == 3) << r.err;  // 3: some trigger late on a loaded machine
  nlohmann::json rehearsal = nlohmann::json::parse(r.out);
  ASSERT_EQ(rehearsal["cameras"].size(), 3u);
  for (const auto& cam : rehearsal["cameras"]) {
    EXPECT_THAT(cam["camera_id"].get<std::string>(), ::testing::StartsWith("hs-"));
    const auto& report = cam["report"];
    // Protobuf's JSON writes 64-bit integers as strings.
    EXPECT_EQ(report["received"], "300") << cam.dump();
    const auto count = [&](const char* key) {
      return report.contains(key) ? std::stoll(report[key].get<std::string>()) : 0;
    };
    EXPECT_EQ(count("fired") + count("late") + count("missed"), 300) << cam.dump();
    EXPECT_GT(count("fired"), 0) << cam.dump();
  }
}

// The simulated world across processes: stage-sim hosts it, each light-node steps on its slot clock and each
// camera-node is triggered by it and renders; over 76 slots every high-speed camera completes 76 frames and every
// machine-vision camera 2, exactly, and every light node took 76 steps.
TEST_F(StageSimTest, TheWorldAcrossProcessesTriggersEveryCameraAndStepsEveryLight) {
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--world", "lockstep", "--world-slots", "76"})));
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  std::map<std::string, uint64_t> expected;
  for (const auto& c : loaded->rig.cameras()) expected[c.id()] = c.role() == v1::CAMERA_ROLE_HIGH_SPEED ? 76 : 2;
  int cameras = 0, lights = 0;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  for (const auto& p : endpoints_.processes()) {
    auto channel = MakeChannel(p.address());
    if (p.kind() == v1::NODE_KIND_CAMERA) {
      auto stub = v1::CameraNode::NewStub(channel);
      v1::CameraStats stats;
      while (true) {
        grpc::ClientContext context;
        ASSERT_TRUE(stub->GetStats(&context, v1::GetStatsRequest(), &stats).ok()) << p.id();
        if (stats.frames_completed() >= expected[p.id()] || std::chrono::steady_clock::now() > deadline) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
      EXPECT_EQ(stats.frames_completed(), expected[p.id()]) << p.id();
      ++cameras;
    } else if (p.kind() == v1::NODE_KIND_LIGHT) {
      auto stub = v1::LightNode::NewStub(channel);
      v1::LightStats stats;
      while (true) {
        grpc::ClientContext context;
        ASSERT_TRUE(stub->GetStats(&context, v1::GetLightStatsRequest(), &stats).ok()) << p.id();
        if (stats.steps() >= 76 || std::chrono::steady_clock::now() > deadline) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
      EXPECT_EQ(stats.steps(), 76u) << p.id();
      EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_ARMED) << p.id();
      ++lights;
    }
  }
  EXPECT_EQ(cameras, 27);
  EXPECT_EQ(lights, 6);
  // Nothing more arrives after the world's end.
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() != v1::NODE_KIND_CAMERA) continue;
    auto stub = v1::CameraNode::NewStub(MakeChannel(p.address()));
    grpc::ClientContext context;
    v1::CameraStats stats;
    ASSERT_TRUE(stub->GetStats(&context, v1::GetStatsRequest(), &stats).ok());
    EXPECT_EQ(stats.frames_completed(), expected[p.id()]) << p.id();
  }

  // Faults go into the running world through stagectl, checked as rig entries are.
  const std::string endpoints = run_dir_.path() + "/endpoints.json";
  const std::string unit = loaded->rig.light_nodes(0).units(0).id();
  CommandResult ok =
      RunCommand({"stagectl", "--endpoints", endpoints, "sim", "fault", unit, "--dead"}, std::chrono::seconds(20));
  EXPECT_EQ(ok.exit.exit_code, 0) << ok.err;
  EXPECT_THAT(ok.out, ::testing::HasSubstr("injected: target: \"" + unit + "\" dead: true"));
  CommandResult misplaced = RunCommand(
      {"stagectl", "--endpoints", endpoints, "sim", "fault", "hs-1", "--delay-us", "50"}, std::chrono::seconds(20));
  EXPECT_EQ(misplaced.exit.exit_code, 2);  // bad input
  EXPECT_THAT(misplaced.err, ::testing::HasSubstr("fault.delay_us: applies to an LED unit or a light node"));
  CommandResult unknown =
      RunCommand({"stagectl", "--endpoints", endpoints, "sim", "fault", "hs-99", "--drop-frames", "0.5"},
                 std::chrono::seconds(20));
  EXPECT_EQ(unknown.exit.exit_code, 2);
  EXPECT_THAT(unknown.err, ::testing::HasSubstr("\"hs-99\" is no LED unit, light node or camera"));
}

// One run of the simulated stage end to end, as the demo does it: the world runs its slots, stage-sim waits until
// every camera delivered what its triggers imply, reports it as JSON, writes the ground truth and takes the stage down.
TEST_F(StageSimTest, UntilRenderedReportsEveryFrameAndWritesTheGroundTruth) {
  TempDir truth;
  CommandResult r = RunCommand({"stage-sim", "--run-dir", run_dir_.path(), "--world-slots", "76", "--until-rendered",
                                "--json", "--set", "sim.render_scale=0.02", "--ground-truth", truth.path()},
                               std::chrono::seconds(300));
  ASSERT_FALSE(r.timed_out);
  ASSERT_EQ(r.exit.exit_code, 0) << r.err;
  EXPECT_THAT(r.err, ::testing::HasSubstr("rendered 276 of 276 frames (100%)"));  // 3 x 76 + 24 x 2
  nlohmann::json j = nlohmann::json::parse(r.out);
  EXPECT_EQ(j["slots"], 76);
  ASSERT_EQ(j["cameras"].size(), 27u);
  for (const auto& [id, cam] : j["cameras"].items()) {
    EXPECT_EQ(cam["frames"], cam["expected"]) << id;
    EXPECT_EQ(cam["expected"], id.rfind("hs-", 0) == 0 ? 76 : 2) << id;
  }
  for (const char* file : {"/frame-000000/pose.json", "/frame-000001/mesh.obj", "/frame-000001/hs-2/depth.exr",
                           "/frame-000000/mv-24/mask.png"}) {
    EXPECT_TRUE(std::filesystem::exists(truth.path() + file)) << file;
  }
  EXPECT_FALSE(std::filesystem::exists(truth.path() + "/frame-000002"));
  EXPECT_THAT(r.err, ::testing::HasSubstr("stage-sim: stage down"));
}

// A 1-second take on the full simulated rig in lockstep, as an operator captures it: every expected frame stored
// (912 per high-speed camera, 24 per machine-vision camera), the alignment self-test passing on every high-speed
// camera, the catalog and the ledger in SQLite read by the sqlite3 shell, and each frame's pattern in the HDF5 file
// read by h5dump, as the schedule says. A second take follows in the same stage; bad requests are refused.
TEST_F(StageSimTest, AOneSecondTakeIsCompleteInTheLedgerTheCatalogAndTheFiles) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  const std::string endpoints = run_dir_.path() + "/endpoints.json";
  CommandResult r =
      RunCommand({"stagectl", "--endpoints", endpoints, "capture", "--seconds", "1", "--name", "one", "--json"},
                 std::chrono::seconds(400));
  ASSERT_FALSE(r.timed_out);
  ASSERT_EQ(r.exit.exit_code, 0) << r.err << r.out;
  EXPECT_THAT(r.err, ::testing::HasSubstr("session: capturing"));
  nlohmann::json take = nlohmann::json::parse(r.out);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE");
  EXPECT_EQ(take["frames"], "24");  // protobuf's JSON writes 64-bit integers as strings
  EXPECT_EQ(take["total"]["expected"], "3312");
  EXPECT_EQ(take["total"]["stored"], "3312");
  ASSERT_EQ(take["cameras"].size(), 27u);
  for (const auto& cam : take["cameras"]) {
    const bool hs = cam["role"] == "CAMERA_ROLE_HIGH_SPEED";
    EXPECT_EQ(cam["counts"]["expected"], hs ? "912" : "24") << cam.dump();
    EXPECT_EQ(cam["counts"]["stored"], cam["counts"]["expected"]) << cam.dump();
  }
  ASSERT_EQ(take["alignment"].size(), 3u);
  for (const auto& a : take["alignment"]) EXPECT_EQ(a["ok"], true) << a.dump();
  const std::string id = take["take_id"];
  const std::string dir = root.path() + "/" + id;

  // The frame files, read by HDF5's own h5dump: 912 frames, pattern k mod 38 in slot k.
  CommandResult dump = RunCommand({"/usr/bin/h5dump", "-d", "/pattern", "-y", "-w", "0", dir + "/cameras/hs-2.h5"},
                                  std::chrono::seconds(30));
  ASSERT_EQ(dump.exit.exit_code, 0) << dump.err;
  EXPECT_THAT(dump.out, ::testing::HasSubstr("SIMPLE { ( 912 ) / ( H5S_UNLIMITED ) }"));
  std::string patterns;
  for (int k = 0; k < 912; ++k) patterns += (k ? ", " : "") + std::to_string(k % 38);
  EXPECT_THAT(dump.out, ::testing::HasSubstr(patterns));
  CommandResult mv = RunCommand({"/usr/bin/h5dump", "-d", "/slot", "-y", "-w", "0", dir + "/cameras/mv-07.h5"},
                                std::chrono::seconds(30));
  EXPECT_THAT(mv.out, ::testing::HasSubstr("19, 57, 95, 133"));
  // Every camera's file, by h5dump: every frame's pattern is its slot's in the schedule (slot mod 38); a high-speed
  // camera has every slot, a machine-vision camera one slot per cycle, always the same pattern.
  for (const auto& cam : take["cameras"]) {
    const std::string file = dir + "/cameras/" + cam["camera_id"].get<std::string>() + ".h5";
    const std::vector<int64_t> slots = ReadH5Column(file, "/slot"), pattern = ReadH5Column(file, "/pattern");
    const bool hs = cam["role"] == "CAMERA_ROLE_HIGH_SPEED";
    ASSERT_EQ(slots.size(), hs ? 912u : 24u) << file;
    ASSERT_EQ(pattern.size(), slots.size()) << file;
    for (size_t i = 0; i < slots.size(); ++i) {
      EXPECT_EQ(pattern[i], slots[i] % 38) << file << " frame " << i;
      EXPECT_EQ(slots[i], hs ? static_cast<int64_t>(i) : slots[0] + 38 * static_cast<int64_t>(i)) << file;
    }
  }

  // The catalog and the ledger, read by the sqlite3 shell.
  CommandResult sql = RunCommand({"/usr/bin/sqlite3", root.path() + "/catalog.sqlite",
                                  "SELECT outcome, frames_stored FROM takes WHERE id='" + id +
                                      "'; SELECT count(*) FROM ledger WHERE take_id='" + id + "' AND reason=0;"},
                                 std::chrono::seconds(30));
  EXPECT_EQ(sql.out, "COMPLETE|3312\n3312\n") << sql.err;
  EXPECT_TRUE(std::filesystem::exists(dir + "/take.json"));

  // Another take in the same stage: the nodes are armed again, the bus runs again.
  CommandResult again =
      RunCommand({"stagectl", "--endpoints", endpoints, "capture", "--frames", "2"}, std::chrono::seconds(200));
  EXPECT_EQ(again.exit.exit_code, 0) << again.err << again.out;
  EXPECT_THAT(again.out, ::testing::HasSubstr("-0002: COMPLETE"));
  CommandResult list = RunCommand({"stagectl", "--endpoints", endpoints, "takes"}, std::chrono::seconds(30));
  EXPECT_THAT(list.out, ::testing::HasSubstr("2 take(s) in " + root.path()));

  // Bad requests change nothing and say why.
  CommandResult unknown =
      RunCommand({"stagectl", "--endpoints", endpoints, "take", "show", "nope"}, std::chrono::seconds(30));
  EXPECT_EQ(unknown.exit.exit_code, 2);
  EXPECT_THAT(unknown.err, ::testing::HasSubstr("no take \"nope\""));
  CommandResult nothing = RunCommand({"stagectl", "--endpoints", endpoints, "capture"}, std::chrono::seconds(30));
  EXPECT_EQ(nothing.exit.exit_code, 2);
  EXPECT_THAT(nothing.err, ::testing::HasSubstr("give a number of frames or seconds above 0"));
}

// A camera that loses three given frames (sim.faults drop_slots): the take is DEGRADED (exit 4), and the ledger names
// exactly those slots as "camera dropped", from the frame counter; the other cameras are complete.
TEST_F(StageSimTest, ATakeWithDroppedFramesIsDegradedWithExactlyThoseSlotsInTheLedger) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  auto rig = ApplyRigOverrides(*loaded, {"sim.render_scale=0.02", "sim.subject.performance=still"});
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto* fault = rig->rig.mutable_sim()->add_faults();
  fault->set_target("hs-2");
  for (int64_t slot : {100, 101, 400}) fault->add_drop_slots(slot);
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  ASSERT_TRUE(google::protobuf::util::MessageToJsonString(rig->rig, &json, print).ok());
  TempDir rig_dir, root;
  ASSERT_NO_FATAL_FAILURE(StartStage({"--config", rig_dir.Write("rig.json", json), "--take-root", root.path()}));
  CommandResult r = RunCommand(
      {"stagectl", "--endpoints", run_dir_.path() + "/endpoints.json", "capture", "--frames", "12", "--json"},
      std::chrono::seconds(300));
  ASSERT_FALSE(r.timed_out);
  EXPECT_EQ(r.exit.exit_code, 4) << r.err << r.out;  // DEGRADED
  nlohmann::json take = nlohmann::json::parse(r.out);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_DEGRADED");
  EXPECT_EQ(take["total"]["expected"], std::to_string(3 * 456 + 24 * 12));
  EXPECT_EQ(take["total"]["stored"], std::to_string(3 * 456 + 24 * 12 - 3));
  EXPECT_THAT(take["hint"].get<std::string>(), ::testing::HasSubstr("hs-2 lost 3 (3 camera dropped)"));
  const std::string id = take["take_id"];
  CommandResult sql = RunCommand({"/usr/bin/sqlite3", root.path() + "/catalog.sqlite",
                                  "SELECT camera_id, slot, reason FROM ledger WHERE take_id='" + id +
                                      "' AND reason != 0 ORDER BY camera_id, slot"},
                                 std::chrono::seconds(30));
  EXPECT_EQ(sql.out, "hs-2|100|1\nhs-2|101|1\nhs-2|400|1\n") << sql.err;
  CommandResult dump =
      RunCommand({"/usr/bin/h5dump", "-d", "/slot", "-y", "-w", "0", root.path() + "/" + id + "/cameras/hs-2.h5"},
                 std::chrono::seconds(30));
  EXPECT_THAT(dump.out, ::testing::HasSubstr("SIMPLE { ( 453 ) / ( H5S_UNLIMITED ) }"));
  EXPECT_THAT(dump.out, ::testing::HasSubstr("98, 99, 102, 103"));
}

}  // namespace
}  // namespace stage::testing

namespace stage::testing {
namespace {

// A small closed head-sized mesh with texture coordinates (a UV sphere, mm) and a 2 x 2 albedo image (binary PPM), as
// a user's head asset: files relative to the rig file that names them.
void WriteTinyHead(const std::string& dir) {
  std::filesystem::create_directories(dir);
  std::string obj;
  constexpr int kRings = 12, kSegments = 24;
  constexpr double kRadius = 90;
  for (int r = 0; r <= kRings; ++r) {
    for (int s = 0; s <= kSegments; ++s) {
      const double theta = M_PI * r / kRings, phi = 2 * M_PI * s / kSegments;
      obj += absl::StrFormat("v %.4f %.4f %.4f\nvt %.5f %.5f\n", kRadius * std::sin(theta) * std::sin(phi),
                             kRadius * std::cos(theta), kRadius * std::sin(theta) * std::cos(phi),
                             static_cast<double>(s) / kSegments, 1.0 - static_cast<double>(r) / kRings);
    }
  }
  auto at = [](int r, int s) { return r * (kSegments + 1) + s + 1; };
  for (int r = 0; r < kRings; ++r) {
    for (int s = 0; s < kSegments; ++s) {
      const int a = at(r, s), b = at(r + 1, s), c = at(r + 1, s + 1), d = at(r, s + 1);
      obj += absl::StrFormat("f %d/%d %d/%d %d/%d\nf %d/%d %d/%d %d/%d\n", a, a, b, b, c, c, a, a, c, c, d, d);
    }
  }
  std::ofstream(dir + "/neutral.obj") << obj;
  std::ofstream(dir + "/albedo.ppm", std::ios::binary)
      << "P6\n2 2\n255\n"
      << std::string("\xc8\x78\x5a\xc8\x78\x5a\xc8\x78\x5a\xc8\x78\x5a", 12);
}

// A user's head named by paths relative to the rig file, the rig run with --set (the nodes then read the run
// directory's rig-set.json): every node finds the files where the rig file pointed, and a take records.
TEST_F(StageSimTest, AHeadAssetRelativeToTheRigFileIsFoundUnderSet) {
  TempDir rigs;
  WriteTinyHead(rigs.path() + "/heads/tiny");
  std::string text = ReadFile(std::string(FASTAGE_SOURCE_DIR) + "/common/rigs/fastage.yaml");
  ASSERT_FALSE(text.empty());
  text += "\nsim:\n  subject:\n    asset: {neutral_obj: heads/tiny/neutral.obj, albedo: heads/tiny/albedo.ppm}\n";
  const std::string rig = rigs.Write("my-rig.yaml", text);
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage({"--config", rig, "--set", "sim.render_scale=0.02", "--take-root", root.path()}));
  CommandResult take = Stagectl({"capture", "--frames", "1", "--json"});
  ASSERT_EQ(take.exit.exit_code, 0) << take.err;
  EXPECT_EQ(nlohmann::json::parse(take.out)["outcome"], "TAKE_OUTCOME_COMPLETE");
}

}  // namespace
}  // namespace stage::testing
