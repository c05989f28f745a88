// stage-controller: owns the rig, watches every node's health, serves the StageController gRPC service.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iostream>

#include "controller_metrics.h"
#include "controller_service.h"
#include "device_monitor.h"
#include "external_sync_generator.h"
#include "health_monitor.h"
#include "light_sync_generator.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"
#include "stage/common/shutdown.h"
#ifdef STAGE_WITH_SIM
#include "stage/sim/world_sync_generator.h"
#endif
#include "stage/timing/timing_tool.h"

int main(int argc, char** argv) {
  stage::BlockShutdownSignals();
  CLI::App app{"The FaStage stage controller: loads the rig, polls every node's health, serves StageController.",
               "stage-controller"};
  stage::CommonFlags flags;
  bool check_only = false;
  stage::AddCommonFlags(app, &flags, /*serves=*/true);
  app.add_flag("--check-config", check_only,
               "Validate the rig file as the controller runs it (every node with its address), print every error of "
               "the file and of the timing verifier, and exit (0 ok, 2 the rig is not valid, 3 the schedule has "
               "errors). A rig for the simulator: `stage-sim --check-config`");
  std::string take_root, world_address;
  app.add_option("--take-root", take_root,
                 "Where takes are recorded and catalogued (default: the rig's storage.root, relative to the working "
                 "directory)");
  app.add_option("--sim-world", world_address,
                 "host:port of stage-sim's simulated world: each take's ground truth, and the slot clock of a rig "
                 "that names no timing.sync_generator");
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  const char* kProgram = "stage-controller";
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  stage::RigValidationOptions options;
  options.require_addresses = true;
  std::vector<std::string> errors;
  auto loaded = stage::LoadRig(flags.config, options, &errors);
  if (check_only) {
    bool addresses = false;
    for (const std::string& e : errors) {
      std::cerr << e << "\n";
      addresses = addresses || e.find(".address:") != std::string::npos;
    }
    if (addresses) {
      std::cerr << "(nodes without an address: a rig that stage-sim runs gets them from stage-sim; check it as "
                   "stage-sim runs it with `stage-sim --check-config --config "
                << flags.config << "`)\n";
    }
    if (!loaded.ok()) return 2;
    auto report = stage::timing::CheckTiming(*loaded, stage::v1::TimingQuery());
    if (!report.ok()) return stage::ReportFatal(kProgram, report.status());
    std::cout << stage::timing::FormatViolations(*report, loaded->source_name);
    if (report->errors() > 0) return 3;
    std::cout << loaded->source_name << ": ok (" << stage::Plural(loaded->rig.cameras_size(), "camera") << ", "
              << stage::Plural(loaded->rig.light_nodes_size(), "light node") << ", "
              << stage::Plural(loaded->rig.processing_workers_size(), "processing worker") << ")\n";
    return 0;
  }
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  if (auto s = stage::UseRigTransportSecurity(*loaded, "controller"); !s.ok()) return stage::ReportFatal(kProgram, s);
  const stage::v1::RigConfig& rig = loaded->rig;

  stage::controller::HealthMonitorOptions monitor_options;
  monitor_options.poll_interval = std::chrono::milliseconds(rig.controller().health_poll_interval_ms());
  monitor_options.timeout = std::chrono::milliseconds(rig.controller().health_timeout_ms());
  monitor_options.clock_sync_interval = std::chrono::milliseconds(rig.controller().clock_sync_interval_ms());
  monitor_options.clock_sync_burst = static_cast<int>(rig.controller().clock_sync_burst());
  // The schedule sets how much clock uncertainty each node tolerates.
  auto timing = stage::timing::CheckTiming(*loaded, {});
  stage::controller::HealthMonitor monitor(
      stage::controller::TargetsFromRig(rig, timing.ok() ? &timing->schedule() : nullptr), monitor_options);
  std::string summary =
      fmt::format("stage {} ({}): {} cameras, {} light nodes, {} processing workers from {}; health poll every {} ms",
                  rig.stage().id(), rig.stage().name(), rig.cameras_size(), rig.light_nodes_size(),
                  rig.processing_workers_size(), loaded->source_name, rig.controller().health_poll_interval_ms());
  monitor.Start();
  const stage::metrics::Registration node_metrics = stage::controller::CollectNodeHealth(&monitor);
  // The nodes' devices, read once a second (a light node's mode, temperature and duty; a camera's link and frames).
  stage::controller::DeviceMonitorOptions device_options;
  device_options.timeout = monitor_options.timeout;
  if (auto s = device_options.Validate(); !s.ok()) return stage::ReportFatal(kProgram, s);
  stage::controller::DeviceMonitor device_monitor(stage::controller::DeviceTargetsFromRig(rig), device_options,
                                                  [&monitor] { monitor.NotifyChange(); });
  device_monitor.Start();
  stage::controller::ControllerService service(*loaded, &monitor);
  service.ShowDevices(&device_monitor);
  {
    stage::controller::CaptureOptions capture;
    std::error_code ec;
    capture.take_root =
        std::filesystem::absolute(take_root.empty() ? rig.storage().root() : take_root, ec).lexically_normal().string();
    // The sync generator, chosen by the rig: the light node timing.sync_generator names drives the slot clock (in the
    // simulated stage its clock line is the world's bus); a rig that names none has an external generator, watched on
    // the input of the light node timing.clock_witness names; a rig with neither, in the simulated stage
    // (--sim-world), the world's own bus. The simulated world also keeps each take's ground truth.
    stage::controller::CaptureDevices devices;
    devices.nodes = stage::controller::GrpcNodeClients();
    const std::string& generator = rig.timing().sync_generator();
    const std::string& witness = rig.timing().clock_witness();
    if (!generator.empty()) {
      for (const auto& node : rig.light_nodes()) {
        if (node.id() == generator) devices.generator = stage::controller::NewLightSyncGenerator(node);
      }
    } else if (!witness.empty()) {
      stage::controller::ExternalGeneratorOptions external;
      external.slot_rate_hz = rig.timing().slot_rate_hz();
      external.end_margin_slots = std::max<int64_t>(1, std::llround(external.slot_rate_hz / 10));
      for (const auto& node : rig.light_nodes()) {
        if (node.id() != witness) continue;
        auto made = stage::controller::NewExternalSyncGenerator(stage::controller::NewGrpcClockWitness(node), external);
        if (!made.ok()) {
          monitor.Stop();
          return stage::ReportFatal(kProgram, made.status());
        }
        devices.generator = *std::move(made);
      }
    } else if (!world_address.empty()) {
#ifdef STAGE_WITH_SIM
      devices.generator = stage::sim::NewWorldSyncGenerator(world_address);
#endif
    } else {
      devices.no_generator =
          "the rig names neither timing.sync_generator (a light node that drives the clock) nor timing.clock_witness "
          "(the light node that timestamps an external generator's edges)";
    }
#ifdef STAGE_WITH_SIM
    if (!world_address.empty()) devices.truth = stage::sim::NewWorldTakeTruth(world_address);
#else
    if (!world_address.empty()) {
      monitor.Stop();
      return stage::ReportFatal(
          kProgram, absl::InvalidArgumentError("--sim-world: this stage-controller is built without the simulator "
                                               "(STAGE_WITH_SIM=OFF)"));
    }
#endif
    if (auto s = service.EnableCapture(capture, std::move(devices)); !s.ok()) {
      monitor.Stop();
      return stage::ReportFatal(kProgram, s);
    }
  }
  int code = stage::ServeUntilSignal(kProgram, flags, rig.controller().listen(), {&service}, summary);
  device_monitor.Stop();
  monitor.Stop();
  return code;
}
