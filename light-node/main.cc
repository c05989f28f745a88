// light-node: serves one LED controller group of the stage (the LightNode gRPC service).
#include <signal.h>

#include <chrono>

#include "backends.h"
#include "light_node.h"
#include "light_service.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/shutdown.h"
#include "stage/sim/world_devices.h"
#include "stage/sim/world_slot_clock.h"

int main(int argc, char** argv) {
  stage::BlockShutdownSignals();
  CLI::App app{"Serves one light node of the FaStage rig (LightNode gRPC service and grpc.health.v1).", "light-node"};
  stage::CommonFlags flags;
  std::string id;
  std::string backend_name;
  stage::AddCommonFlags(app, &flags, /*serves=*/true);
  app.add_option("--id", id, "Id of this light node in the rig file")->required();
  app.add_option("--backend", backend_name, "Use this backend instead of the rig's (sim, gpiod, modbus)");
  std::string world_address;
  app.add_option(
      "--sim-world", world_address,
      "host:port of stage-sim's simulated world: the sim backend steps on its slot clock and lights its LEDs "
      "(armed by the controller for each take)");
  double device_wait_s = 0;
  app.add_option("--device-wait-s", device_wait_s,
                 "When the node's device (its Modbus board, its GPIO chip) cannot be reached at start-up, try again "
                 "every second for this long, saying so each time, before giving up (a board powered after its node); "
                 "0 gives up at once")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 86400.0));
  bool self_arm = false;
  app.add_flag("--sim-self-arm", self_arm,
               "With --sim-world: load the table from the rig's schedule and arm at once (a world without takes)");
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  const char* kProgram = "light-node";
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  auto loaded = stage::LoadRig(flags.config);
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  auto entry = stage::FindLightNode(*loaded, id);
  if (!entry.ok()) return stage::ReportFatal(kProgram, entry.status());
  const stage::v1::LightNodeConfig& config = **entry;
  stage::v1::LightBackend backend = config.backend();
  if (!backend_name.empty()) {
    auto parsed = stage::light::ParseLightBackend(backend_name);
    if (!parsed.ok()) return stage::ReportFatal(kProgram, parsed.status());
    backend = *parsed;
  }
  auto driver = stage::light::CreateLightDriver(backend, config, loaded->rig.timing().slot_rate_hz());
  // A device not there yet (Unavailable: a board that does not answer; NotFound: no such chip) is tried again for
  // --device-wait-s; any other error (bad settings, a board of another kind) is final at once.
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::duration<double>(device_wait_s);
  while (!driver.ok() && (absl::IsUnavailable(driver.status()) || absl::IsNotFound(driver.status())) &&
         std::chrono::steady_clock::now() < give_up) {
    const double left = std::chrono::duration<double>(give_up - std::chrono::steady_clock::now()).count();
    stage::Logger("light.node")
        ->warn("{}; trying again every second for another {:.0f} s", driver.status().message(), left);
    if (auto sig = stage::WaitForShutdownSignal(std::chrono::milliseconds(1000))) {
      stage::Logger("light.node")->info("stopped (signal {}) while waiting for the device", *sig);
      return 0;
    }
    driver = stage::light::CreateLightDriver(backend, config, loaded->rig.timing().slot_rate_hz());
  }
  if (!driver.ok()) return stage::ReportFatal(kProgram, driver.status());
  // Declared before the node: the world outlives the driver, which leaves it when destroyed.
  std::unique_ptr<stage::sim::WorldClient> world;
  if (!world_address.empty()) {
    auto* sim_driver = dynamic_cast<stage::sim::SimLightDriver*>(driver->get());
    if (sim_driver == nullptr) {
      return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--sim-world needs the sim backend"));
    }
    auto opened = stage::sim::OpenNodeWorld(*loaded, world_address);
    if (!opened.ok()) return stage::ReportFatal(kProgram, opened.status());
    world = std::move(opened->client);
    if (auto s = stage::sim::JoinLightNode(
            sim_driver, *opened->scene, config.id(), world.get(), [] { raise(SIGKILL); }, self_arm);
        !s.ok()) {
      return stage::ReportFatal(kProgram, s);
    }
  }
  stage::light::LightNodeOptions node_options;
  node_options.slot_rate_hz = loaded->rig.timing().slot_rate_hz();
  node_options.take_length_s = loaded->rig.timing().take_length_s();
  auto node = stage::light::LightNode::Create(config, std::move(*driver), stage::RigHash(loaded->rig), node_options);
  if (!node.ok()) return stage::ReportFatal(kProgram, node.status());
  if (loaded->rig.timing().sync_generator() == config.id()) {
    // The rig's sync generator: the controller runs the slot clock through this node, on the gpiod driver's clock
    // output; in the simulated stage the node's clock line is the world's bus.
    if (!world_address.empty()) (*node)->SetSlotClock(stage::sim::NewWorldSlotClock(world_address, config.id()));
    if (!(*node)->drives_slot_clock()) {
      stage::Logger("light.node")
          ->warn(
              "{} is the rig's timing.sync_generator, but its {} backend has no clock output here (a simulated "
              "node needs --sim-world): the controller's takes are refused",
              config.id(), stage::light::LightBackendName(backend));
    }
  }
  std::string summary =
      fmt::format("light node {}: {} LED units on {} channels, backend {}, rig {}", config.id(), config.units_size(),
                  config.channel_count(), stage::light::LightBackendName(backend), loaded->source_name);

  stage::light::LightService service(node->get());
  return stage::ServeUntilSignal(kProgram, flags, config.address().empty() ? "127.0.0.1:0" : config.address(),
                                 {&service}, summary);
}
