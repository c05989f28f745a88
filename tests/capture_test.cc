// Takes on the full simulated stage, driven as an operator drives them (stagectl), with the session and its faults:
// pause and resume give one take whose ledger shows the gap and nothing else lost (and watchers see every state);
// an armed take starts on capture and an aborted one keeps what it recorded; bad requests change nothing; a camera
// node killed mid-take, a frame file that hits its size limit, a light node late enough to blend patterns and a
// light table off by one are each found, with the exact ledger entries. The ledger is read with the sqlite3 shell and
// the frame files with HDF5's own h5dump.
#include <grpcpp/grpcpp.h>
#include <sys/resource.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <mutex>
#include <nlohmann/json.hpp>
#include <set>
#include <thread>

#include "absl/strings/str_join.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/take_names.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "stage/v1/sim.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

class CaptureTest : public SimulatedStageTest {
 protected:
  CaptureTest() { stagectl_timeout_ = std::chrono::seconds(60); }

  std::string Sql(const std::string& root, const std::string& query) {
    CommandResult r = RunCommand({"/usr/bin/sqlite3", root + "/catalog.sqlite", query}, std::chrono::seconds(30));
    EXPECT_EQ(r.exit.exit_code, 0) << r.err;
    return r.out;
  }

  // The /slot column of a frame file, read by h5dump (on a copy, repaired with h5clear as docs/storage.md says, when
  // the writer died with the file open), as long as /status: the column a frame's append writes last, so a writer
  // killed between columns leaves /slot one frame longer.
  std::vector<int64_t> FileSlots(const std::string& path) {
    CommandResult check = RunCommand({"/usr/bin/h5dump", "-H", path}, std::chrono::seconds(30));
    std::string file = path;
    if (check.exit.exit_code != 0) {
      file = run_dir_.path() + "/repaired.h5";
      std::filesystem::copy_file(path, file, std::filesystem::copy_options::overwrite_existing);
      EXPECT_EQ(RunCommand({"/usr/bin/h5clear", "-s", "--increment", file}, std::chrono::seconds(30)).exit.exit_code,
                0);
    }
    std::vector<int64_t> slots = ReadH5Column(file, "/slot");
    slots.resize(std::min(slots.size(), ReadH5Column(file, "/status").size()));
    return slots;
  }

  std::string SlotsOf(const std::string& root, const std::string& take, const std::string& camera, int reason) {
    return Sql(root, "SELECT group_concat(slot, ',') FROM (SELECT slot FROM ledger WHERE take_id='" + take +
                         "' AND camera_id='" + camera + "' AND reason=" + std::to_string(reason) + " ORDER BY slot)");
  }

  // The frames a camera node has written of its take, asked every 100 ms until there are `at_least` (or `within` has
  // passed: the last answer).
  int64_t FramesWritten(const v1::SimProcess& node, int64_t at_least, std::chrono::seconds within) {
    auto camera = v1::CameraNode::NewStub(MakeChannel(node.address()));
    const auto deadline = std::chrono::steady_clock::now() + within;
    int64_t written = 0;
    while (written < at_least && std::chrono::steady_clock::now() < deadline) {
      grpc::ClientContext context;
      v1::CameraStats stats;
      if (camera->GetStats(&context, v1::GetStatsRequest(), &stats).ok()) written = stats.take_frames_written();
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    return written;
  }

  // The world's bus as the test sees it: who started its last run, and who has called Run, EndRun and GetRun.
  v1::WorldRunReply WorldBus() {
    auto world = v1::SimWorld::NewStub(MakeChannel(endpoints_.world()));
    grpc::ClientContext context;
    v1::GetRunRequest get;
    get.set_requested_by("test");
    v1::WorldRunReply run;
    EXPECT_TRUE(world->GetRun(&context, get, &run).ok());
    return run;
  }

  const v1::SimProcess* Process(const std::string& id) const {
    for (const auto& p : endpoints_.processes()) {
      if (p.id() == id) return &p;
    }
    return nullptr;
  }
};

std::string Digits(int64_t n) { return std::to_string(n); }

// Pause at a frame boundary and resume: one take, COMPLETE, its ledger lists the gap's slots as paused and nothing
// else lost; the frame file goes on after the gap; a watcher of the stage's status saw every state as it came.
// Requests that do not fit the session's state are refused with the state named.
TEST_F(CaptureTest, PauseAndResumeGiveOneTakeWithAGapAndNothingElseLost) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  CommandResult idle_pause = Stagectl({"pause"});
  EXPECT_EQ(idle_pause.exit.exit_code, 2);
  EXPECT_THAT(idle_pause.err, HasSubstr("the session is idle, not capturing"));

  // A watcher of the stage's status, as the console will be.
  std::mutex states_mutex;
  std::vector<std::string> states;
  grpc::ClientContext watch_context;
  auto stub = v1::StageController::NewStub(MakeChannel(endpoints_.controller()));
  std::thread watcher([&] {
    v1::WatchStageStatusRequest request;
    request.set_heartbeat_ms(5000);
    auto reader = stub->WatchStageStatus(&watch_context, request);
    v1::StageStatus status;
    while (reader->Read(&status)) {
      std::lock_guard<std::mutex> lock(states_mutex);
      const std::string state = SessionStateName(status.session_state());
      if (states.empty() || states.back() != state) states.push_back(state);
    }
    (void)reader->Finish();
  });
  struct StopWatching {
    grpc::ClientContext& context;
    std::thread& thread;
    ~StopWatching() {
      context.TryCancel();
      if (thread.joinable()) thread.join();
    }
  } stop_watching{watch_context, watcher};

  auto capture = SpawnStagectl({"capture", "--frames", "12", "--name", "paused once", "--json"}, "capture");
  ASSERT_NE(capture, nullptr);
  ASSERT_TRUE(WaitForSession("capturing", std::chrono::seconds(120))) << ReadFile(run_dir_.path() + "/capture.err");
  std::this_thread::sleep_for(std::chrono::seconds(2));

  // A preview of a camera's latest full-on frame reached the controller: small, PNG.
  // (The first full-on frame comes once the camera has rendered it.)
  CommandResult preview;
  for (int i = 0; i < 60; ++i) {
    preview = Stagectl({"preview", "hs-2", "-o", run_dir_.path() + "/hs-2.png", "--json"});
    if (preview.exit.exit_code == 0 || preview.err.find("no preview yet") == std::string::npos) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }
  ASSERT_EQ(preview.exit.exit_code, 0) << preview.err;
  nlohmann::json meta = nlohmann::json::parse(preview.out);
  EXPECT_GT(meta["width"].get<int>(), 0);
  EXPECT_LE(meta["width"].get<int>(), 256);
  EXPECT_LE(meta["height"].get<int>(), 256);
  EXPECT_EQ(meta["frame"]["camera_id"], "hs-2");
  EXPECT_EQ(ReadFile(run_dir_.path() + "/hs-2.png").substr(1, 3), "PNG");
  CommandResult no_camera = Stagectl({"preview", "hs-9"});
  EXPECT_EQ(no_camera.exit.exit_code, 2);
  EXPECT_THAT(no_camera.err, HasSubstr("\"hs-9\" is no camera of the rig"));

  CommandResult busy = Stagectl({"capture", "--frames", "2"});
  EXPECT_EQ(busy.exit.exit_code, 2);
  EXPECT_THAT(busy.err, HasSubstr("the session is capturing; wait for it"));
  CommandResult early_resume = Stagectl({"resume"});
  EXPECT_EQ(early_resume.exit.exit_code, 2);
  EXPECT_THAT(early_resume.err, HasSubstr("the session is capturing, not paused"));

  CommandResult pause = Stagectl({"pause", "--json"});
  ASSERT_EQ(pause.exit.exit_code, 0) << pause.err;
  const int64_t p = std::stoll(nlohmann::json::parse(pause.out)["slot"].get<std::string>());
  EXPECT_EQ(p % 38, 0);
  EXPECT_GT(p, 0);
  EXPECT_LT(p, 456);
  EXPECT_EQ(SessionState(), "paused");
  std::this_thread::sleep_for(std::chrono::seconds(1));
  CommandResult resume = Stagectl({"resume", "--json"});
  ASSERT_EQ(resume.exit.exit_code, 0) << resume.err;
  const int64_t r = std::stoll(nlohmann::json::parse(resume.out)["slot"].get<std::string>());
  EXPECT_EQ(r % 38, 0);
  EXPECT_GE(r, p + 38);

  auto exit = capture->Wait(std::chrono::seconds(400));
  ASSERT_TRUE(exit.has_value());
  EXPECT_EQ(exit->exit_code, 0) << ReadFile(run_dir_.path() + "/capture.err");
  nlohmann::json take = nlohmann::json::parse(ReadFile(run_dir_.path() + "/capture.out"));
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE");
  EXPECT_EQ(take["total"]["expected"], Digits(3 * 456 + 24 * 12));
  EXPECT_EQ(take["total"]["stored"], Digits(3 * 456 + 24 * 12));
  // The gap: every high-speed slot of it, and each machine-vision camera's one slot per frame of it.
  const int64_t gap = r - p;
  EXPECT_EQ(take["total"]["paused"], Digits(3 * gap + 24 * gap / 38));
  ASSERT_EQ(take["paused"].size(), 1u);
  EXPECT_EQ(take["paused"][0]["first"], Digits(p));
  EXPECT_EQ(take["paused"][0]["end"], Digits(r));
  EXPECT_EQ(take["slots"], Digits(r + 456 - p));

  const std::string id = take["take_id"];
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id + "' AND reason=7"),
            Digits(3 * gap + 24 * gap / 38) + "\n");
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id + "' AND reason NOT IN (0, 7)"), "0\n");
  // hs-2's file: 456 frames, slot p - 1 followed by slot r.
  const std::vector<int64_t> slots = FileSlots(root.path() + "/" + id + "/cameras/hs-2.h5");
  ASSERT_EQ(slots.size(), 456u);
  EXPECT_EQ(slots[static_cast<size_t>(p) - 1], p - 1);
  EXPECT_EQ(slots[static_cast<size_t>(p)], r);
  EXPECT_EQ(slots.back(), r + 456 - p - 1);

  // Every state reached the watcher, in order.
  ASSERT_TRUE(WaitForSession("idle", std::chrono::seconds(10)));
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  watch_context.TryCancel();
  watcher.join();
  std::lock_guard<std::mutex> lock(states_mutex);
  EXPECT_THAT(states, ::testing::ElementsAre("idle", "configuring", "armed", "capturing", "paused", "capturing",
                                             "finalizing", "idle"));
}

// `stagectl arm` leaves a take armed; capture starts it; abort ends it at the next slot, keeps every frame it
// recorded (the ledger covers exactly the slots that ran, all stored) and marks it aborted. A take aborted while
// armed ran no slot at all.
TEST_F(CaptureTest, AnArmedTakeStartsOnCaptureAndAnAbortKeepsWhatItRecorded) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  CommandResult zero = Stagectl({"capture", "--frames", "0"});
  EXPECT_EQ(zero.exit.exit_code, 2);
  CommandResult idle_abort = Stagectl({"abort"});
  EXPECT_EQ(idle_abort.exit.exit_code, 2);
  EXPECT_THAT(idle_abort.err, HasSubstr("the session is idle"));

  CommandResult arm = Stagectl({"arm", "--frames", "24", "--name", "armed first", "--json"});
  ASSERT_EQ(arm.exit.exit_code, 0) << arm.err;
  const std::string id = nlohmann::json::parse(arm.out)["take_id"];
  EXPECT_EQ(SessionState(), "armed");
  CommandResult again = Stagectl({"arm", "--frames", "2"});
  EXPECT_EQ(again.exit.exit_code, 2);
  EXPECT_THAT(again.err, HasSubstr("the session is armed"));
  CommandResult other = Stagectl({"capture", "--frames", "5"});
  EXPECT_EQ(other.exit.exit_code, 2);
  EXPECT_THAT(other.err, HasSubstr("is armed for 24 frames, not 5"));

  auto capture = SpawnStagectl({"capture", "--json"}, "capture");
  ASSERT_NE(capture, nullptr);
  ASSERT_TRUE(WaitForSession("capturing", std::chrono::seconds(60))) << ReadFile(run_dir_.path() + "/capture.err");
  std::this_thread::sleep_for(std::chrono::seconds(3));
  CommandResult abort = Stagectl({"abort", "--json"});
  ASSERT_EQ(abort.exit.exit_code, 0) << abort.err;
  const int64_t a = std::stoll(nlohmann::json::parse(abort.out)["slot"].get<std::string>());
  EXPECT_GT(a, 0);
  EXPECT_LT(a, 912);
  auto exit = capture->Wait(std::chrono::seconds(300));
  ASSERT_TRUE(exit.has_value());
  EXPECT_EQ(exit->exit_code, 1);  // FAILED: aborted
  nlohmann::json take = nlohmann::json::parse(ReadFile(run_dir_.path() + "/capture.out"));
  EXPECT_EQ(take["take_id"], id);
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_FAILED");
  EXPECT_EQ(take["aborted"], true);
  EXPECT_THAT(take["hint"].get<std::string>(), HasSubstr("aborted by the operator at slot " + Digits(a)));
  EXPECT_EQ(Sql(root.path(), "SELECT state FROM takes WHERE id='" + id + "'"), "aborted\n");
  // Exactly the slots that ran, every one stored.
  EXPECT_EQ(Sql(root.path(),
                "SELECT count(*), min(slot), max(slot) FROM ledger WHERE take_id='" + id + "' AND camera_id='hs-1'"),
            absl::StrCat(a, "|0|", a - 1, "\n"));
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id + "' AND reason != 0"), "0\n");
  EXPECT_EQ(take["total"]["stored"], take["total"]["expected"]);
  EXPECT_EQ(FileSlots(root.path() + "/" + id + "/cameras/hs-1.h5").size(), static_cast<size_t>(a));

  // Armed, then aborted: nothing ran.
  ASSERT_EQ(Stagectl({"arm", "--frames", "2"}).exit.exit_code, 0);
  CommandResult drop = Stagectl({"abort"});
  EXPECT_EQ(drop.exit.exit_code, 0) << drop.err;
  EXPECT_THAT(drop.out, HasSubstr("aborted before it started"));
  EXPECT_EQ(SessionState(), "idle");
  EXPECT_EQ(Sql(root.path(), "SELECT state, outcome FROM takes ORDER BY id DESC LIMIT 1"), "aborted|FAILED\n");
}

// A camera node killed mid-take: the take goes on and ends DEGRADED; every frame the node wrote before it died is
// in its file (read by h5dump after h5clear) and stored in the ledger; its other slots are "node down"; every other
// camera is complete.
TEST_F(CaptureTest, ACameraNodeKilledMidTakeLeavesItsFramesAndTheRestNodeDown) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  const v1::SimProcess* victim = Process("mv-03");
  ASSERT_NE(victim, nullptr);
  auto capture = SpawnStagectl({"capture", "--frames", "12", "--json"}, "capture");
  ASSERT_NE(capture, nullptr);
  ASSERT_GE(FramesWritten(*victim, 3, std::chrono::seconds(120)), 3);
  ASSERT_EQ(kill(victim->pid(), SIGKILL), 0);

  auto exit = capture->Wait(std::chrono::seconds(300));
  ASSERT_TRUE(exit.has_value());
  EXPECT_EQ(exit->exit_code, 4) << ReadFile(run_dir_.path() + "/capture.err");  // DEGRADED
  nlohmann::json take = nlohmann::json::parse(ReadFile(run_dir_.path() + "/capture.out"));
  const std::string id = take["take_id"];
  const std::vector<int64_t> in_file = FileSlots(root.path() + "/" + id + "/cameras/mv-03.h5");
  ASSERT_GE(in_file.size(), 3u);
  ASSERT_LT(in_file.size(), 12u);
  EXPECT_EQ(SlotsOf(root.path(), id, "mv-03", 0), absl::StrJoin(in_file, ",") + "\n");
  std::vector<int64_t> down;
  for (int64_t k = 0; k < 456; ++k) {
    if (k % 38 == in_file[0] % 38 && std::find(in_file.begin(), in_file.end(), k) == in_file.end()) down.push_back(k);
  }
  EXPECT_EQ(SlotsOf(root.path(), id, "mv-03", 3), absl::StrJoin(down, ",") + "\n");
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id +
                                 "' AND camera_id != 'mv-03' AND "
                                 "reason != 0"),
            "0\n");
  EXPECT_THAT(take["hint"].get<std::string>(), HasSubstr("mv-03 lost " + Digits(12 - in_file.size()) + " (" +
                                                         Digits(12 - in_file.size()) + " node down)"));
}

// The rig's sync generator is light node lights-gpio-1: its clock line is the world's bus. The controller runs the
// take's clock through the node and never calls the world's bus itself; when the node is killed mid-take its line
// goes quiet, the take ends DEGRADED (continue-degraded), every expected slot is stored or "sync generator lost", and
// no light node is left armed.
TEST_F(CaptureTest, TheGeneratorLightNodeDrivesTheClockAndItsDeathEndsTheTake) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  const v1::SimProcess* generator = Process("lights-gpio-1");
  ASSERT_NE(generator, nullptr);
  auto capture = SpawnStagectl({"capture", "--frames", "40", "--json"}, "capture");
  ASSERT_NE(capture, nullptr);
  const v1::SimProcess* witness = Process("mv-01");
  ASSERT_NE(witness, nullptr);
  ASSERT_GE(FramesWritten(*witness, 3, std::chrono::seconds(180)), 3);
  const v1::WorldRunReply during = WorldBus();
  EXPECT_EQ(during.started_by(), "lights-gpio-1");
  EXPECT_EQ(during.bus_calls().count("controller"), 0u) << "the controller called the world's bus";
  EXPECT_GT(during.bus_calls().at("lights-gpio-1"), 0);
  ASSERT_EQ(kill(generator->pid(), SIGKILL), 0);

  auto exit = capture->Wait(std::chrono::seconds(300));
  ASSERT_TRUE(exit.has_value());
  EXPECT_EQ(exit->exit_code, 4) << ReadFile(run_dir_.path() + "/capture.err");  // DEGRADED
  nlohmann::json take = nlohmann::json::parse(ReadFile(run_dir_.path() + "/capture.out"));
  const std::string id = take["take_id"];
  EXPECT_THAT(take["hint"].get<std::string>(), HasSubstr("the sync generator was lost: light node lights-gpio-1"));
  // Every slot of the 40 frames the take was asked for: 24 machine-vision cameras one a frame, 3 high-speed all 38.
  EXPECT_EQ(take["total"]["expected"].get<std::string>(), Digits(24 * 40 + 3 * 40 * 38));
  const std::string lost = Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id +
                                                "' AND reason=" + Digits(v1::LOSS_REASON_SYNC_GENERATOR_LOST));
  EXPECT_GT(std::stoll(lost), 0);
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id + "' AND reason NOT IN (0, 7, " +
                                 Digits(v1::LOSS_REASON_SYNC_GENERATOR_LOST) + ")"),
            "0\n");
  EXPECT_EQ(WorldBus().bus_calls().count("controller"), 0u);
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() != v1::NODE_KIND_LIGHT || p.id() == "lights-gpio-1") continue;
    auto light = v1::LightNode::NewStub(MakeChannel(p.address()));
    grpc::ClientContext context;
    v1::LightStats stats;
    ASSERT_TRUE(light->GetStats(&context, v1::GetLightStatsRequest(), &stats).ok()) << p.id();
    EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_IDLE) << p.id() << " is left armed";
  }
}

// An external generator (a signal generator the operator started before the take) runs free on the world's bus; the
// rig names no generator node, and lights-gpio-2 timestamps the clock (timing.clock_witness). Every light node is a
// driver that sees the edges (no fake Modbus boards: a board that steps on every edge from arming cannot start at a
// planned edge of a free-running clock, and the take would be refused). The take's T0 is the witness's measured edge
// of a cycle-aligned slot well after the edge it last saw; the lights start their tables there; the take is COMPLETE,
// its high-speed cameras aligned, its ledger exact; and neither the controller nor any node called the world's bus.
TEST_F(CaptureTest, AnExternalGeneratorRunningBeforeTheTakeGivesItsT0FromTheWitnessEdge) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(
      ControlPlaneScene({"--set", "sim.modbus_fakes=false", "--set", "timing.sync_generator=\"\"", "--set",
                         "timing.clock_witness=lights-gpio-2", "--set",
                         "light_nodes[lights-gpio-1].gpiod.drives_slot_clock=false", "--take-root", root.path()})));
  auto world = v1::SimWorld::NewStub(MakeChannel(endpoints_.world()));
  {
    // The operator starts the signal generator: it runs until stopped (a run of a billion slots, 12 days).
    grpc::ClientContext context;
    v1::RunWorldRequest run;
    run.set_slots(1'000'000'000);
    run.set_align_slots(38);
    run.set_requested_by("signal-generator");
    v1::WorldRunReply started;
    ASSERT_TRUE(world->Run(&context, run, &started).ok());
    EXPECT_EQ(started.first_slot(), 0);
  }
  auto exit = SpawnStagectl({"capture", "--frames", "6", "--json"}, "capture")->Wait(std::chrono::seconds(300));
  ASSERT_TRUE(exit.has_value());
  EXPECT_EQ(exit->exit_code, 0) << ReadFile(run_dir_.path() + "/capture.err");
  nlohmann::json take = nlohmann::json::parse(ReadFile(run_dir_.path() + "/capture.out"));
  const std::string id = take["take_id"];
  EXPECT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE") << take["hint"];
  EXPECT_EQ(take["total"]["expected"].get<std::string>(), Digits(24 * 6 + 3 * 6 * 38));
  EXPECT_EQ(take["total"]["stored"], take["total"]["expected"]);
  ASSERT_EQ(take["alignment"].size(), 3u);
  for (const auto& a : take["alignment"]) EXPECT_TRUE(a["ok"].get<bool>()) << a.dump();
  // T0 is the edge of a slot the pattern cycle divides, on the world's clock (lockstep: ns since slot 0), and not the
  // first edge of the generator's run: the clock was running when the take began.
  const int64_t t0 = std::stoll(take["t0_bus_ns"].get<std::string>());
  const int64_t first_slot = std::llround(static_cast<double>(t0) * 912 / 1e9);
  EXPECT_GT(first_slot, 0);
  EXPECT_EQ(first_slot % 38, 0) << first_slot;
  EXPECT_NEAR(static_cast<double>(t0), first_slot * 1e9 / 912, 2.0);
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id + "' AND reason != 0"), "0\n");
  // The bus is the signal generator's: nobody else started, ended or asked for a run.
  const v1::WorldRunReply bus = WorldBus();
  EXPECT_EQ(bus.started_by(), "signal-generator");
  for (const auto& [who, calls] : bus.bus_calls()) {
    EXPECT_TRUE(who == "signal-generator" || who == "test") << who << " called the world's bus " << calls << " times";
  }
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() != v1::NODE_KIND_LIGHT) continue;
    auto light = v1::LightNode::NewStub(MakeChannel(p.address()));
    grpc::ClientContext context;
    v1::LightStats stats;
    ASSERT_TRUE(light->GetStats(&context, v1::GetLightStatsRequest(), &stats).ok()) << p.id();
    EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_IDLE) << p.id() << " is left armed";
  }
}

// A frame file that reaches its size limit (the node's RLIMIT_FSIZE, as a full disk would): the node stops writing
// cleanly and reports it; the frames before are in the file and stored, every later one "write failed".
TEST_F(CaptureTest, AFrameFileAtItsSizeLimitStopsCleanlyWithTheLossesAttributed) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  const v1::SimProcess* node = Process("mv-05");
  ASSERT_NE(node, nullptr);
  struct rlimit limit {};
  limit.rlim_cur = limit.rlim_max = 48 * 1024;
  ASSERT_EQ(prlimit(node->pid(), RLIMIT_FSIZE, &limit, nullptr), 0) << std::strerror(errno);
  CommandResult r = Stagectl({"capture", "--frames", "12", "--json"}, std::chrono::seconds(300));
  EXPECT_EQ(r.exit.exit_code, 4) << r.err;  // DEGRADED
  nlohmann::json take = nlohmann::json::parse(r.out);
  const std::string id = take["take_id"];
  const std::vector<int64_t> in_file = FileSlots(root.path() + "/" + id + "/cameras/mv-05.h5");
  ASSERT_GE(in_file.size(), 1u);
  ASSERT_LT(in_file.size(), 12u);
  EXPECT_EQ(SlotsOf(root.path(), id, "mv-05", 0), absl::StrJoin(in_file, ",") + "\n");
  EXPECT_EQ(Sql(root.path(), "SELECT count(*), min(slot) > " + Digits(in_file.back()) + " FROM ledger WHERE take_id='" +
                                 id + "' AND camera_id='mv-05' AND reason=5"),
            Digits(12 - in_file.size()) + "|1\n");
  EXPECT_EQ(Sql(root.path(), "SELECT count(*) FROM ledger WHERE take_id='" + id +
                                 "' AND camera_id != 'mv-05' AND "
                                 "reason != 0"),
            "0\n");
  for (const auto& cam : take["cameras"]) {
    if (cam["camera_id"] == "mv-05") {
      EXPECT_THAT(cam["error"].get<std::string>(), HasSubstr("mv-05.h5"));
    }
  }
}

// The alignment self-test on takes whose frames are all stored: a light node whose light comes 600 us late blends
// two patterns into its frames, and light tables stepped once too often are off by one. Both are DEGRADED with the
// high-speed cameras' self-test saying why; the ledger has no loss.
TEST_F(CaptureTest, TheSelfTestFindsBlendedPatternsAndATableOffByOne) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  std::vector<std::string> lights;
  for (const auto& n : endpoints_.processes()) {
    if (n.kind() == v1::NODE_KIND_LIGHT) lights.push_back(n.id());
  }
  ASSERT_GE(lights.size(), 2u);
  CommandResult late = Stagectl({"sim", "fault", lights[1], "--delay-us", "600"});
  ASSERT_EQ(late.exit.exit_code, 0) << late.err;
  CommandResult blended = Stagectl({"capture", "--frames", "3", "--json"}, std::chrono::seconds(300));
  EXPECT_EQ(blended.exit.exit_code, 4) << blended.err << blended.out;
  nlohmann::json take = nlohmann::json::parse(blended.out);
  EXPECT_EQ(take["total"]["stored"], take["total"]["expected"]);
  ASSERT_EQ(take["alignment"].size(), 3u);
  for (const auto& a : take["alignment"]) {
    EXPECT_FALSE(a.value("ok", false)) << a.dump();
    EXPECT_EQ(a.value("shift", 0), 0) << a.dump();
  }

  // Every light node's board steps once more at the next take's first edge: its table runs one pattern ahead.
  for (const std::string& id : lights) {
    CommandResult f = Stagectl({"sim", "fault", id, "--extra-steps", "1", "--delay-us", "0"});
    ASSERT_EQ(f.exit.exit_code, 0) << f.err;
  }
  CommandResult shifted = Stagectl({"capture", "--frames", "3", "--json"}, std::chrono::seconds(300));
  EXPECT_EQ(shifted.exit.exit_code, 4) << shifted.err << shifted.out;
  take = nlohmann::json::parse(shifted.out);
  EXPECT_EQ(take["total"]["stored"], take["total"]["expected"]);
  ASSERT_EQ(take["alignment"].size(), 3u);
  for (const auto& a : take["alignment"]) {
    EXPECT_FALSE(a.value("ok", false)) << a.dump();
    EXPECT_EQ(std::abs(a.value("shift", 0)), 1) << a.dump();
  }
}

}  // namespace
}  // namespace stage::testing
