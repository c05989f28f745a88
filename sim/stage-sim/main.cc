// stage-sim: brings a whole simulated FaStage up on this machine, keeps it up until SIGINT/SIGTERM (or until a
// given command finishes), and takes it down with no process left behind.
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <iostream>
#include <nlohmann/json.hpp>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/string_view.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/common/shutdown.h"
#include "stage/common/subprocess.h"
#include "stage/sim/face_template.h"
#include "stage/sim/ground_truth.h"
#include "stage/sim/scene.h"
#include "stage/sim/stage_supervisor.h"
#include "stage/sim/world_devices.h"
#include "stage/sim/world_service.h"
#include "stage/timing/schedule.h"
#include "stage/timing/timing_tool.h"
#include "stage/v1/camera_node.grpc.pb.h"
#if STAGE_WITH_ARAVIS
#include "stage/sim/gige_fake_camera.h"
#endif
#if STAGE_WITH_MODBUS
#include "stage/sim/fake_led_board.h"
#endif

namespace {

constexpr const char* kProgram = "stage-sim";

// The frames camera `index` fires in slots [0, slots) by the schedule.
int64_t ExpectedFrames(const stage::sim::SimScene& scene, int index, int64_t slots) {
  return stage::timing::FiringsInTake(scene.schedule().cameras(index), slots);
}

// Waits until every camera node has delivered the frames its trigger plan implies for the world's `slots`, showing
// progress; then prints (or writes as JSON) frames per camera and the wall time. Gives up when no frame arrives for
// `patience`.
absl::Status WaitUntilRendered(const stage::sim::SimScene& scene, const stage::v1::SimEndpoints& endpoints,
                               int64_t slots, std::chrono::steady_clock::time_point since,
                               std::chrono::seconds patience, bool json) {
  struct Cam {
    std::string id;
    int64_t expected = 0, frames = 0;
    std::unique_ptr<stage::v1::CameraNode::Stub> stub;
  };
  std::vector<Cam> cams;
  int64_t total = 0;
  for (const auto& p : endpoints.processes()) {
    if (p.kind() != stage::v1::NODE_KIND_CAMERA) continue;
    const int index = scene.CameraIndex(p.id());
    if (index < 0) continue;
    Cam c;
    c.id = p.id();
    c.expected = ExpectedFrames(scene, index, slots);
    c.stub = stage::v1::CameraNode::NewStub(stage::MakeChannel(p.address()));
    total += c.expected;
    cams.push_back(std::move(c));
  }
  int64_t done = -1;
  auto last_progress = std::chrono::steady_clock::now();
  auto last_line = last_progress - std::chrono::seconds(10);
  while (true) {
    int64_t now_done = 0;
    for (Cam& c : cams) {
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
      stage::v1::CameraStats stats;
      if (c.stub->GetStats(&context, stage::v1::GetStatsRequest(), &stats).ok()) {
        c.frames = static_cast<int64_t>(stats.frames_completed());
      }
      now_done += std::min(c.frames, c.expected);
    }
    const auto now = std::chrono::steady_clock::now();
    if (now_done != done) {
      done = now_done;
      last_progress = now;
    }
    const bool finished = done >= total;
    if (finished || now - last_line >= std::chrono::seconds(2)) {
      last_line = now;
      std::cerr << absl::StrFormat("stage-sim: rendered %d of %d frames (%.0f%%), %.1f s\n", done, total,
                                   total > 0 ? 100.0 * static_cast<double>(done) / static_cast<double>(total) : 100.0,
                                   std::chrono::duration<double>(now - since).count());
    }
    if (finished) break;
    if (now - last_progress > patience) {
      std::string short_of;
      for (const Cam& c : cams) {
        if (c.frames < c.expected)
          absl::StrAppend(&short_of, short_of.empty() ? "" : ", ", c.id, " ", c.frames, "/", c.expected);
      }
      return absl::DeadlineExceededError(absl::StrCat("no frame for ", patience.count(), " s; short: ", short_of));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
  const double virtual_s = static_cast<double>(slots) / scene.base().slot_rate_hz();
  if (json) {
    nlohmann::json j;
    j["slots"] = slots;
    j["virtual_s"] = virtual_s;
    j["wall_s"] = wall_s;
    j["frames"] = total;
    j["render_scale"] = scene.rig().sim().render_scale();
    for (const Cam& c : cams) j["cameras"][c.id] = {{"frames", c.frames}, {"expected", c.expected}};
    std::cout << j.dump(2) << std::endl;
  } else {
    std::cout << absl::StrFormat(
                     "stage-sim: %d slots (%.3f s of the stage) rendered by %d cameras at render scale %g: %d frames "
                     "in %.1f s (%.0f frames/s)",
                     slots, virtual_s, cams.size(), scene.rig().sim().render_scale(), total, wall_s,
                     static_cast<double>(total) / wall_s)
              << std::endl;
  }
  return absl::OkStatus();
}

// stage-sim --check-config: the rig as stage-sim would run it, every error at once.
int CheckConfig(const std::string& config, const std::vector<std::string>& overrides, bool with_world) {
  std::vector<std::string> errors;
  auto loaded = stage::LoadRig(config, {}, &errors);  // stage-sim assigns every node's address
  for (const std::string& e : errors) std::cerr << e << "\n";
  if (!loaded.ok()) {
    if (errors.empty()) std::cerr << loaded.status().message() << "\n";
    return 2;
  }
  if (!overrides.empty()) {
    loaded = stage::ApplyRigOverrides(*loaded, overrides);
    if (!loaded.ok()) {
      std::cerr << loaded.status().message() << "\n";
      return 2;
    }
  }
  if (with_world) {
    // The simulated subject and dome, as the world builds them (a head asset's files are read here).
    auto scene = stage::sim::SimScene::FromLoadedRig(*loaded);
    if (!scene.ok()) {
      std::cerr << scene.status().message() << "\n";
      return 2;
    }
    for (const std::string& note : (*scene)->notes()) std::cout << "note: " << note << "\n";
  }
  auto report = stage::timing::CheckTiming(*loaded, stage::v1::TimingQuery());
  if (!report.ok()) {
    std::cerr << report.status().message() << "\n";
    return 2;
  }
  std::cout << stage::timing::FormatViolations(*report, loaded->source_name);
  const auto& rig = loaded->rig;
  if (report->errors() > 0) return 3;
  std::cout << loaded->source_name << ": ok as stage-sim runs it (" << stage::Plural(rig.cameras_size(), "camera")
            << ", " << stage::Plural(rig.light_nodes_size(), "light node") << ", "
            << stage::Plural(rig.processing_workers_size(), "processing worker") << ")\n";
  return 0;
}

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
  bool until_rendered = false, json = false;
  app.add_flag("--until-rendered", until_rendered,
               "With --world-slots: wait until every camera has delivered the frames the world's slots trigger "
               "(progress on stderr), print frames and wall time, and take the stage down");
  app.add_flag("--json", json, "--until-rendered: print the summary as JSON");
  app.add_option("--take-root", options.take_root,
                 "Where the controller records takes (default: the rig's storage.root, relative to here)");
  app.add_flag("--metrics", options.metrics,
               "Serve Prometheus metrics from stage-sim (its world) and from every process it starts, each on a "
               "loopback port of its own: the endpoint file lists them (metrics, processes[].metrics)");
  bool check_config = false;
  app.add_flag("--check-config", check_config,
               "Check the rig as stage-sim runs it (node addresses are stage-sim's to assign; --set applied): print "
               "every error of the rig file, the simulated subject and the timing verifier, and exit (0 ok, 2 the rig "
               "is not valid, 3 the schedule has errors); starts nothing");
  std::string ground_truth_dir;
  app.add_option("--ground-truth", ground_truth_dir,
                 "With --world-slots: also write the simulator's ground truth of the virtual frames the world runs "
                 "(every camera) into this directory (docs/simulator.md#ground-truth)");
  std::string world_listen = "127.0.0.1:0";
  app.add_option("--world-listen", world_listen,
                 "Where the simulated world serves its nodes, host:port (another address than loopback needs the "
                 "rig's mutual TLS)")
      ->capture_default_str();
  std::vector<std::string> places;
  app.add_option("--place", places,
                 "WHO=NETNS/HOST: run WHO (a node id, or camera, light, worker, controller) in network namespace NETNS "
                 "(ip netns exec), listening on HOST there: hosts a test makes (the rig's mutual TLS needed); "
                 "repeatable");
  std::string export_template_dir;
  app.add_option(
      "--export-face-template", export_template_dir,
      "Write the face template processing fits (the shipped procedural head's face: face-template.obj and "
      "face-template.json, and its shape and expression model face-model.f32, as processing/data/ holds them; "
      "docs/assets.md) into this directory, and exit; "
      "starts nothing");
  app.footer(
      "Examples: stage-sim -- stagectl status\n"
      "          stage-sim --world-slots 912 --until-rendered --set sim.render_scale=0.03  # one second");
  if (auto code = stage::ParseCommandLine(app, own_argc, argv)) return *code;
  for (const std::string& place : places) {
    const size_t eq = place.find('='), slash = place.find('/', eq == std::string::npos ? 0 : eq);
    if (eq == std::string::npos || slash == std::string::npos || eq == 0) {
      return stage::ReportFatal(kProgram, absl::InvalidArgumentError(absl::StrCat(
                                              "--place ", place, ": expected WHO=NETNS/HOST (e.g. camera=h1/10.77.0.11)")));
    }
    options.placements[place.substr(0, eq)] = {place.substr(eq + 1, slash - eq - 1), place.substr(slash + 1)};
  }
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (!export_template_dir.empty()) {
    const auto head = stage::sim::HeadModel::Procedural(/*seed=*/1);
    stage::sim::FaceTemplateData face = stage::sim::MakeFaceTemplate(*head);
    face.model =
        stage::sim::MakeFaceModel(face, *head, stage::sim::kFaceModelFirstIdentity, stage::sim::kFaceModelIdentities);
    if (face.model.identity.empty()) {
      return stage::ReportFatal(kProgram, absl::InternalError("--export-face-template: the face model came out empty"));
    }
    if (auto s = stage::sim::WriteFaceTemplate(face, export_template_dir); !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
    std::cout << "face template written to " << export_template_dir << "/face-template.{obj,json} and face-model.f32 ("
              << face.model.identity.size() << " identity components, " << face.model.expression.size()
              << " expressions)\n";
    return 0;
  }
  if ((until_rendered || !ground_truth_dir.empty()) && (world_slots <= 0 || world_mode == "none")) {
    return stage::ReportFatal(
        kProgram, absl::InvalidArgumentError("--until-rendered and --ground-truth need a world and --world-slots N"));
  }
  if (until_rendered && !command.empty()) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--until-rendered takes no command"));
  }
  options.rig = flags.config;
  if (check_config) return CheckConfig(options.rig, options.overrides, world_mode != "none");
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
  auto loaded = stage::LoadRig(options.rig);
  if (loaded.ok() && !options.overrides.empty()) loaded = stage::ApplyRigOverrides(*loaded, options.overrides);
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  // stage-sim serves the world and asks the controller whether the stage is up: as "sim" when the rig says mutual TLS.
  if (auto s = stage::UseRigTransportSecurity(*loaded, "sim"); !s.ok()) return stage::ReportFatal(kProgram, s);
  stage::MetricsEndpoint metrics;
  if (options.metrics) {
    flags.metrics_listen = "127.0.0.1:0";
    auto started = stage::StartMetrics(kProgram, flags);
    if (!started.ok()) return stage::ReportFatal(kProgram, started.status());
    metrics = *std::move(started);
    options.own_metrics = metrics.address();
  }
  // The world first: the nodes join it as they start.
  std::shared_ptr<const stage::sim::SimScene> scene;
  std::unique_ptr<stage::sim::World> world;
  std::unique_ptr<stage::sim::WorldService> world_service;
  std::unique_ptr<stage::RpcServer> world_server;
  stage::metrics::Registration world_metrics;  // before `world` is destroyed, the collector that reads it is gone
  if (world_mode != "none") {
    auto created = stage::sim::SimScene::FromLoadedRig(*loaded);
    if (!created.ok()) return stage::ReportFatal(kProgram, created.status());
    scene = *created;
    const bool lockstep = world_mode == "lockstep";
    stage::sim::WorldOptions world_options = scene->MakeWorldOptions(lockstep, 0);
    world_options.end_slot = world_slots > 0 ? world_slots : -1;
    // Without --world-slots the bus runs only for the controller's takes.
    world_options.open_run = world_slots > 0;
    options.self_armed_world = world_slots > 0;
    world = std::make_unique<stage::sim::World>(scene->dome(), world_options);
    stage::sim::ApplyUnitFaults(*scene, world.get());
    world_metrics = stage::metrics::Registry::Default().AddCollector([w = world.get()](stage::metrics::Writer& out) {
      out.Gauge("stage_sim_world_slot", "The slot edge the simulated world stands at (lockstep) or last passed", {},
                static_cast<double>(w->current_slot()));
    });
    stage::v1::WorldInfo info;
    info.set_slot_rate_hz(world_options.slot_rate_hz);
    info.set_lockstep(lockstep);
    info.set_t0_ns(0);
    world_service =
        std::make_unique<stage::sim::WorldService>(world.get(), info, [scene](const stage::v1::SimFault& f) {
          if (f.has_packet_loss() || f.has_link_down_at_s() || f.has_link_down_s()) {
            // The fake GigE cameras take these from the rig when they start; nothing would apply them now.
            return absl::InvalidArgumentError(
                "packet_loss and link_down are set in the rig (sim.faults), not injected into a running stage");
          }
          return scene->CheckFault(f);
        });
    // A take's ground truth, into its directory, when the controller asks (docs/simulator.md#ground-truth).
    world_service->set_ground_truth_writer([scene](const stage::v1::GroundTruthRequest& r) {
      stage::sim::GroundTruthOptions gt;
      gt.first_frame = r.first_frame();
      gt.last_frame = r.first_frame() + r.frames();
      gt.name_offset = r.has_name_offset() ? r.name_offset() : r.first_frame();
      gt.cameras.assign(r.cameras().begin(), r.cameras().end());
      gt.camera_maps = !r.scene_only();
      return stage::sim::WriteGroundTruth(*scene, r.dir(), gt);
    });
    // The world's devices are processes of this machine: one that dies closes its connection at once. A device slow
    // to answer a keepalive ping (a starved machine, a stopped process) is still in the world: the lockstep world waits
    // for it, so the ping's timeout is long rather than the default's 5 s.
    stage::RpcServerOptions world_server_options;
    world_server_options.listen = world_listen;
    world_server_options.keepalive_timeout_ms = 600'000;
    auto server = stage::RpcServer::Start(world_server_options, {world_service.get()});
    if (!server.ok()) return stage::ReportFatal(kProgram, server.status());
    world_server = std::move(*server);
    options.world_address = world_server->address();
  }
  // Fake GigE Vision cameras (sim.gige_fakes), up before the nodes that open them; down before the world.
#if STAGE_WITH_ARAVIS
  std::vector<std::unique_ptr<stage::sim::WorldClient>> fake_clients;
  std::vector<std::unique_ptr<stage::sim::GigEFakeCamera>> fakes;
#endif
  if (scene != nullptr && scene->rig().sim().gige_fakes()) {
#if STAGE_WITH_ARAVIS
    for (const auto& c : scene->rig().cameras()) {
      if (c.backend() != stage::v1::CAMERA_BACKEND_ARAVIS) continue;
      auto fake_options = stage::sim::GigEFakeOptionsFromRig(*scene, c.id());
      if (!fake_options.ok()) return stage::ReportFatal(kProgram, fake_options.status());
      fake_clients.push_back(stage::sim::LocalWorldClient(world.get()));
      auto fake = stage::sim::GigEFakeCamera::Create(scene, fake_clients.back().get(), *fake_options);
      if (!fake.ok()) return stage::ReportFatal(kProgram, fake.status());
      fakes.push_back(std::move(*fake));
    }
    log->info("{} fake GigE Vision camera(s) up", fakes.size());
#else
    return stage::ReportFatal(
        kProgram, absl::FailedPreconditionError("sim.gige_fakes: this build has no Aravis (STAGE_WITH_ARAVIS=OFF)"));
#endif
  }
  // Fake LED boards (sim.modbus_fakes) on loopback, one per modbus light node, up before the nodes that connect to
  // them: the nodes read the rig with modbus.tcp set to their board; down before the world.
#if STAGE_WITH_MODBUS
  std::vector<std::unique_ptr<stage::sim::WorldClient>> board_clients;
  std::vector<std::unique_ptr<stage::sim::FakeLedBoard>> boards;
#endif
  if (scene != nullptr && scene->rig().sim().modbus_fakes()) {
#if STAGE_WITH_MODBUS
    for (int i = 0; i < scene->rig().light_nodes_size(); ++i) {
      const stage::v1::LightNodeConfig& n = scene->rig().light_nodes(i);
      if (n.backend() != stage::v1::LIGHT_BACKEND_MODBUS) continue;
      auto board_options = stage::sim::FakeLedBoardOptionsForNode(n, static_cast<uint32_t>(i + 1));
      if (!board_options.ok()) return stage::ReportFatal(kProgram, board_options.status());
      auto board = stage::sim::FakeLedBoard::Start(*board_options);
      if (!board.ok()) return stage::ReportFatal(kProgram, board.status());
      board_clients.push_back(stage::sim::LocalWorldClient(world.get()));
      if (absl::Status s = (*board)->JoinStage(*scene, n.id(), board_clients.back().get(), options.self_armed_world);
          !s.ok()) {
        return stage::ReportFatal(kProgram, s);
      }
      const std::string path = absl::StrCat("light_nodes[", n.id(), "].modbus.tcp.");
      options.overrides.push_back(path + "host=127.0.0.1");
      options.overrides.push_back(absl::StrCat(path, "port=", (*board)->port()));
      boards.push_back(*std::move(board));
    }
    log->info("{} fake LED board(s) up", boards.size());
#else
    return stage::ReportFatal(kProgram, absl::FailedPreconditionError(
                                            "sim.modbus_fakes: this build has no libmodbus (STAGE_WITH_MODBUS=OFF)"));
#endif
  }
  auto stop_world = [&] {
#if STAGE_WITH_ARAVIS
    fakes.clear();  // they leave the world
#endif
#if STAGE_WITH_MODBUS
    boards.clear();
#endif
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
                            static_cast<int>(seconds * 10) / 10.0,
                            " s: ", stage::Plural(rig.cameras_size(), "camera node"), ", ",
                            stage::Plural(rig.light_nodes_size(), "light node"), ", ",
                            stage::Plural(rig.processing_workers_size(), "processing worker"), ", controller at ",
                            supervisor.endpoints().controller(), "; endpoints in ", supervisor.endpoints_path())
            << std::endl;

  const auto world_started = std::chrono::steady_clock::now();
  if (world) {
    world->Start();
    std::cerr << (world_slots > 0 ? absl::StrCat("stage-sim: the ", world_mode, " world runs ", world_slots,
                                                 " slots (world at ", options.world_address, ")")
                                  : absl::StrCat("stage-sim: the ", world_mode,
                                                 " world runs takes (stagectl capture; "
                                                 "world at ",
                                                 options.world_address, ")"))
              << std::endl;
  }

  int exit_code = 0;
  if (until_rendered) {
    const absl::Status s =
        WaitUntilRendered(*scene, supervisor.endpoints(), world_slots, world_started, std::chrono::seconds(120), json);
    if (!s.ok()) {
      std::cerr << "stage-sim: " << s.message() << std::endl;
      exit_code = 1;
    }
  }
  if (!ground_truth_dir.empty() && exit_code == 0) {
    stage::sim::GroundTruthOptions gt;
    const int64_t cycle = stage::timing::CycleLength(scene->schedule());
    gt.last_frame = (world_slots + cycle - 1) / cycle;
    gt.progress = [](int done, int total) {
      if (done == total || done % 27 == 0) std::cerr << "stage-sim: ground truth " << done << "/" << total << std::endl;
    };
    if (absl::Status s = stage::sim::WriteGroundTruth(*scene, ground_truth_dir, gt); !s.ok()) {
      std::cerr << "stage-sim: ground truth: " << s.message() << std::endl;
      exit_code = 1;
    } else {
      std::cerr << "stage-sim: ground truth of " << gt.last_frame << " frame(s) in " << ground_truth_dir << std::endl;
    }
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

  while (!until_rendered) {
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
