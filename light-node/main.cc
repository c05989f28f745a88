// light-node: serves one LED controller group of the stage (the LightNode gRPC service).
#include <signal.h>

#include <chrono>

#include "light_backends.h"
#include "light_node.h"
#include "light_service.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"
#include "stage/common/shutdown.h"
#ifdef STAGE_WITH_SIM
#include "stage/sim/node_backends.h"
#endif

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
  if (auto s = stage::UseRigTransportSecurity(*loaded, "light/" + id); !s.ok()) return stage::ReportFatal(kProgram, s);
  auto entry = stage::FindLightNode(*loaded, id);
  if (!entry.ok()) return stage::ReportFatal(kProgram, entry.status());
  const stage::v1::LightNodeConfig& config = **entry;
  stage::v1::LightBackend backend = config.backend();
  if (!backend_name.empty()) {
    auto parsed = stage::light::ParseLightBackend(backend_name);
    if (!parsed.ok()) return stage::ReportFatal(kProgram, parsed.status());
    backend = *parsed;
  }
  // The backends this program has: the hardware ones, and the simulator's when built with it.
  stage::light::LightBackends backends;
  stage::light::RegisterHardwareLightBackends(&backends);
#ifdef STAGE_WITH_SIM
  stage::sim::RegisterSimLightBackend(&backends, [] { raise(SIGKILL); });
#endif
  if (!world_address.empty() && backend != stage::v1::LIGHT_BACKEND_SIM) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--sim-world needs the sim backend"));
  }
  stage::light::LightBackendContext context;
  context.rig = &*loaded;
  context.slot_rate_hz = loaded->rig.timing().slot_rate_hz();
  context.world_address = world_address;
  context.self_arm = self_arm;
  auto parts = backends.Create(backend, config, context);
  // A device not there yet (Unavailable: a board that does not answer; NotFound: no such chip) is tried again for
  // --device-wait-s; any other error (bad settings, a board of another kind) is final at once.
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::duration<double>(device_wait_s);
  while (!parts.ok() && (absl::IsUnavailable(parts.status()) || absl::IsNotFound(parts.status())) &&
         std::chrono::steady_clock::now() < give_up) {
    const double left = std::chrono::duration<double>(give_up - std::chrono::steady_clock::now()).count();
    stage::Logger("light.node")
        ->warn("{}; trying again every second for another {:.0f} s", parts.status().message(), left);
    if (auto sig = stage::WaitForShutdownSignal(std::chrono::milliseconds(1000))) {
      stage::Logger("light.node")->info("stopped (signal {}) while waiting for the device", *sig);
      return 0;
    }
    parts = backends.Create(backend, config, context);
  }
  if (!parts.ok()) return stage::ReportFatal(kProgram, parts.status());
  // Declared before the node: what the driver needs (the simulated world) outlives it.
  const std::shared_ptr<void> keep = parts->keep;
  stage::light::LightNodeOptions node_options;
  node_options.slot_rate_hz = loaded->rig.timing().slot_rate_hz();
  node_options.take_length_s = loaded->rig.timing().take_length_s();
  auto node =
      stage::light::LightNode::Create(config, std::move(parts->driver), stage::RigHash(loaded->rig), node_options);
  if (!node.ok()) return stage::ReportFatal(kProgram, node.status());
  if (parts->slot_clock != nullptr) (*node)->SetSlotClock(std::move(parts->slot_clock));
  if (loaded->rig.timing().sync_generator() == config.id() && !(*node)->drives_slot_clock()) {
    // The rig's sync generator: the controller runs the slot clock through this node (gpiod's clock output; in the
    // simulated stage, the world's bus).
    stage::Logger("light.node")
        ->warn(
            "{} is the rig's timing.sync_generator, but its {} backend has no clock output here (a simulated node "
            "needs --sim-world): the controller's takes are refused",
            config.id(), stage::light::LightBackendName(backend));
  }
  std::string summary =
      fmt::format("light node {}: {} LED units on {} channels, backend {}, rig {}", config.id(), config.units_size(),
                  config.channel_count(), stage::light::LightBackendName(backend), loaded->source_name);

  stage::light::LightService service(node->get());
  return stage::ServeUntilSignal(kProgram, flags, config.address().empty() ? "127.0.0.1:0" : config.address(),
                                 {&service}, summary);
}
