// stage-sim: brings a whole simulated FaStage up on this machine, keeps it up until SIGINT/SIGTERM (or until a
// given command finishes), and takes it down with no process left behind.
#include <signal.h>
#include <unistd.h>

#include <filesystem>
#include <iostream>

#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_server.h"
#include "stage/common/shutdown.h"
#include "stage/common/subprocess.h"
#include "stage/sim/scene.h"
#include "stage/sim/stage_supervisor.h"
#include "stage/sim/world_devices.h"
#include "stage/sim/world_service.h"

namespace {

constexpr const char* kProgram = "stage-sim";

std::string SelfDir() {
  std::error_code ec;
  auto self = std::filesystem::read_symlink("/proc/self/exe", ec);
  return ec ? std::string(".") : self.parent_path().string();
}

}  // namespace

int main(int argc, char** argv) {
  stage::BlockShutdownSignals(/*include_sigchld=*/true);
  // Everything after "--" is a command to run once the stage is up.
  std::vector<std::string> command;
  int own_argc = argc;
  for (int i = 1; i < argc; ++i) {
    if (absl::string_view(argv[i]) == "--") {
      own_argc = i;
      for (int j = i + 1; j < argc; ++j) command.emplace_back(argv[j]);
      break;
    }
  }

  CLI::App app{
      "Brings up a simulated FaStage on this machine (every node on loopback, sim backends), waits until "
      "every node is up, writes an endpoint file, and keeps the stage up until SIGINT/SIGTERM. With "
      "'-- COMMAND ARGS...' it runs COMMAND once the stage is up (FASTAGE_ENDPOINTS set), takes the stage "
      "down when it finishes, and exits with its exit code.",
      "stage-sim"};
  stage::CommonFlags flags;
  stage::sim::StageSupervisorOptions options;
  options.run_dir = stage::DefaultSimRunDir();
  options.bin_dir = SelfDir();
  int startup_timeout_ms = 60000;
  int grace_ms = 3000;
  stage::AddCommonFlags(app, &flags, /*serves=*/false);
  app.add_option("--run-dir", options.run_dir, "Directory for the endpoint file, logs and the effective rig")
      ->capture_default_str();
  app.add_option("--bin-dir", options.bin_dir, "Directory holding the node programs")->capture_default_str();
  app.add_option("--startup-timeout-ms", startup_timeout_ms, "How long the stage may take to come up")
      ->capture_default_str()
      ->check(CLI::Range(1, 3600000));
  app.add_option("--grace-ms", grace_ms, "Time children get between SIGTERM and SIGKILL")
      ->capture_default_str()
      ->check(CLI::Range(0, 600000));
  app.add_option("--listen", options.controller_listen,
                 "Where the stage controller listens, host:port (port 0 picks a free port)")
      ->capture_default_str();
  app.add_option("--child-log-level", options.child_log_level, "--log-level passed to every child");
  app.add_option("--set", options.overrides,
                 "Override a rig field for every node, PATH=VALUE (e.g. sim.render_scale=0.03); repeatable");
  std::string world_mode = "lockstep";
  int64_t world_slots = 0;
  app.add_option("--world", world_mode,
                 "The simulated world the nodes share (docs/simulator.md): lockstep (time moves a slot once every "
                 "device is done with it; deterministic), realtime (slots come with the wall clock; devices that fall "
                 "behind miss them), or none (test-pattern cameras)")
      ->capture_default_str()
      ->check(CLI::IsMember({"lockstep", "realtime", "none"}));
  app.add_option("--world-slots", world_slots,
                 "Run the world for this many slots once the stage is up (912 = one second of the shipped rig); "
                 "0 leaves it waiting")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40));
  app.footer("Example: stage-sim -- stagectl status");
  if (auto code = stage::ParseCommandLine(app, own_argc, argv)) return *code;
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  options.rig = flags.config;
  options.startup_timeout = std::chrono::milliseconds(startup_timeout_ms);
  options.grace = std::chrono::milliseconds(grace_ms);
  if (!options.child_log_level.empty()) {
    if (auto s = stage::ValidateLogLevels(options.child_log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  }
  if (!command.empty()) {
    if (auto found = stage::FindExecutable(command[0]); !found.ok())
      return stage::ReportFatal(kProgram, found.status());
  }

  auto log = stage::Logger("sim.stage");
  // The world first: the nodes join it as they start.
  std::shared_ptr<const stage::sim::SimScene> scene;
  std::unique_ptr<stage::sim::World> world;
  std::unique_ptr<stage::sim::WorldService> world_service;
  std::unique_ptr<stage::RpcServer> world_server;
  if (world_mode != "none") {
    auto loaded = stage::LoadRig(options.rig);
    if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
    if (!options.overrides.empty()) {
      loaded = stage::ApplyRigOverrides(*loaded, options.overrides);
      if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
    }
    auto created = stage::sim::SimScene::FromLoadedRig(*loaded);
    if (!created.ok()) return stage::ReportFatal(kProgram, created.status());
    scene = *created;
    const bool lockstep = world_mode == "lockstep";
    stage::sim::WorldOptions world_options = scene->MakeWorldOptions(lockstep, 0);
    world_options.end_slot = world_slots > 0 ? world_slots : -1;
    world = std::make_unique<stage::sim::World>(scene->dome(), world_options);
    stage::sim::ApplyUnitFaults(*scene, world.get());
    stage::v1::WorldInfo info;
    info.set_slot_rate_hz(world_options.slot_rate_hz);
    info.set_lockstep(lockstep);
    info.set_t0_ns(0);
    world_service = std::make_unique<stage::sim::WorldService>(world.get(), info);
    auto server = stage::RpcServer::Start({}, {world_service.get()});
    if (!server.ok()) return stage::ReportFatal(kProgram, server.status());
    world_server = std::move(*server);
    options.world_address = world_server->address();
  }
  auto stop_world = [&] {
    if (!world) return;
    world->Stop();
    world_service->Shutdown();
    world_server->Shutdown();
  };
  stage::sim::StageSupervisor supervisor(options);
  auto started_at = std::chrono::steady_clock::now();
  if (absl::Status s = supervisor.Start(); !s.ok()) {
    stop_world();
    return stage::ReportFatal(kProgram, s);
  }
  const auto& rig = supervisor.rig().rig;
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started_at).count();
  std::cerr << absl::StrCat("stage-sim: stage \"", rig.stage().id(), "\" is up in ",
                            static_cast<int>(seconds * 10) / 10.0, " s: ", rig.cameras_size(), " camera nodes, ",
                            rig.light_nodes_size(), " light nodes, ", rig.processing_workers_size(),
                            " processing worker(s), controller at ", supervisor.endpoints().controller(),
                            "; endpoints in ", supervisor.endpoints_path())
            << std::endl;

  if (world && world_slots > 0) {
    world->Start();
    std::cerr << absl::StrCat("stage-sim: the ", world_mode, " world runs ", world_slots, " slots (world at ",
                              options.world_address, ")")
              << std::endl;
  }

  std::unique_ptr<stage::Subprocess> user_command;
  if (!command.empty()) {
    stage::SubprocessOptions sp;
    sp.argv = command;
    sp.env = {"FASTAGE_ENDPOINTS=" + supervisor.endpoints_path(),
              "FASTAGE_CONTROLLER=" + supervisor.endpoints().controller()};
    sp.null_stdin = false;
    auto spawned = stage::Subprocess::Spawn(sp);
    if (!spawned.ok()) {
      supervisor.Stop();
      return stage::ReportFatal(kProgram, spawned.status());
    }
    user_command = std::move(*spawned);
  }

  int exit_code = 0;
  while (true) {
    std::optional<int> sig = stage::WaitForShutdownSignal(std::chrono::milliseconds(200));
    if (sig && (*sig == SIGINT || *sig == SIGTERM)) {
      log->info("{} received; taking the stage down", *sig == SIGINT ? "SIGINT" : "SIGTERM");
      if (user_command) user_command->Terminate(options.grace);
      break;
    }
    for (const std::string& line : supervisor.ReapExited()) log->error("{}", line);
    if (user_command) {
      if (auto done = user_command->Poll()) {
        exit_code = done->signal != 0 ? 128 + done->signal : done->exit_code;
        break;
      }
    }
  }
  // The world stops first, so that no node waits on it while it is taken down.
  stop_world();
  int killed = supervisor.Stop();
  std::cerr << "stage-sim: stage down"
            << (killed > 0 ? absl::StrCat(" (", killed, " process(es) needed SIGKILL)") : std::string()) << std::endl;
  return exit_code;
}
