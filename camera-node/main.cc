// camera-node: serves one camera of the stage (the CameraNode gRPC service) with the backend the rig names.
#include <signal.h>

#include <iostream>
#include <nlohmann/json.hpp>

#include "camera_backends.h"
#include "camera_node.h"
#include "camera_service.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"
#include "stage/common/shutdown.h"
#ifdef STAGE_WITH_SIM
#include "stage/sim/node_backends.h"
#endif
#if STAGE_WITH_ARAVIS
#include "aravis_camera_device.h"
#endif

namespace {

// camera-node --list: what discovery finds, as a table or JSON.
int ListCameras(bool json) {
#if STAGE_WITH_ARAVIS
  const std::vector<stage::camera::AravisCameraInfo> cameras = stage::camera::ListAravisCameras();
  if (json) {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& c : cameras) {
      out.push_back({{"id", c.id},
                     {"vendor", c.vendor},
                     {"model", c.model},
                     {"serial", c.serial},
                     {"address", c.address},
                     {"protocol", c.protocol}});
    }
    std::cout << out.dump(2) << "\n";
    return 0;
  }
  if (cameras.empty()) {
    std::cout << "no cameras found (GigE Vision discovery on every interface, USB3 Vision)\n";
    return 0;
  }
  std::cout << fmt::format("{:<32} {:<12} {:<16} {:<16} {:<16} {}\n", "ID", "VENDOR", "MODEL", "SERIAL", "ADDRESS",
                           "PROTOCOL");
  for (const auto& c : cameras) {
    std::cout << fmt::format("{:<32} {:<12} {:<16} {:<16} {:<16} {}\n", c.id, c.vendor, c.model, c.serial, c.address,
                             c.protocol);
  }
  return 0;
#else
  (void)json;
  return stage::ReportFatal("camera-node",
                            absl::FailedPreconditionError("this build has no aravis backend (STAGE_WITH_ARAVIS=OFF)"));
#endif
}

}  // namespace

int main(int argc, char** argv) {
  stage::BlockShutdownSignals();
  // A frame file that reaches the file size limit (RLIMIT_FSIZE) fails its write with EFBIG, which the recorder
  // reports as lost frames, instead of the signal killing the node.
  signal(SIGXFSZ, SIG_IGN);
  CLI::App app{"Serves one camera of the FaStage rig (CameraNode gRPC service and grpc.health.v1).", "camera-node"};
  stage::CommonFlags flags;
  std::string id;
  std::string backend_name;
  stage::AddCommonFlags(app, &flags, /*serves=*/true);
  app.add_option("--id", id, "Id of this camera in the rig file (required to serve)");
  bool list = false, json = false;
  app.add_flag("--list", list, "List the GigE Vision and USB3 Vision cameras Aravis finds, then exit");
  app.add_flag("--json", json, "With --list: one JSON array");
  app.add_option("--backend", backend_name, "Use this backend instead of the rig's (sim, aravis)");
  std::string world_address;
  app.add_option("--sim-world", world_address,
                 "host:port of stage-sim's simulated world: the sim backend is triggered by its slot clock and renders "
                 "the stage");
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  const char* kProgram = "camera-node";
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (list) return ListCameras(json);
  if (id.empty()) return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--id is required"));

  auto loaded = stage::LoadRig(flags.config);
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  if (auto s = stage::UseRigTransportSecurity(*loaded, "camera/" + id); !s.ok()) return stage::ReportFatal(kProgram, s);
  auto camera = stage::FindCamera(*loaded, id);
  if (!camera.ok()) return stage::ReportFatal(kProgram, camera.status());
  const stage::v1::CameraConfig& config = **camera;
  stage::v1::CameraBackend backend = config.backend();
  if (!backend_name.empty()) {
    auto parsed = stage::camera::ParseCameraBackend(backend_name);
    if (!parsed.ok()) return stage::ReportFatal(kProgram, parsed.status());
    backend = *parsed;
  }

  // The backends this program has: the hardware one, and the simulator's when built with it.
  stage::camera::CameraBackends backends;
  stage::camera::RegisterHardwareCameraBackends(&backends);
#ifdef STAGE_WITH_SIM
  stage::sim::RegisterSimCameraBackend(&backends, [] { raise(SIGKILL); });
#endif
  if (!world_address.empty() && backend != stage::v1::CAMERA_BACKEND_SIM) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError("--sim-world needs the sim backend"));
  }
  stage::RealClock clock(stage::RealClock::Kind::kRealtime);
  stage::camera::CameraBackendContext context;
  context.rig = &*loaded;
  context.clock = &clock;
  context.world_address = world_address;
  auto parts = backends.Create(backend, config, context);
  if (!parts.ok()) return stage::ReportFatal(kProgram, parts.status());
  // Declared before the node: what the device needs (the simulated world) outlives it.
  const std::shared_ptr<void> keep = parts->keep;
  auto node = stage::camera::CameraNode::Create(config, std::move(parts->device), stage::RigHash(loaded->rig));
  if (!node.ok()) return stage::ReportFatal(kProgram, node.status());
  // A camera on the trigger line acquires from the start, waiting for the line's edges (in the world: the world's
  // trigger bus); frames outside a take are counted and not recorded. Scheduled software triggers start it per stream.
  if (parts->start_now) {
    if (auto s = (*node)->device().Start(node->get()); !s.ok()) return stage::ReportFatal(kProgram, s);
  }
  std::string summary = fmt::format("camera {}: {}, {}x{} {} at {} fps, exposure {} us, backend {}, rig {}",
                                    config.id(), stage::CameraRoleName(config.role()), config.width(), config.height(),
                                    stage::PixelFormatName(config.pixel_format()), config.frame_rate_hz(),
                                    config.exposure_us(), stage::camera::CameraBackendName(backend),
                                    loaded->source_name);

  stage::camera::CameraService service(node->get());
  return stage::ServeUntilSignal(kProgram, flags, config.address().empty() ? "127.0.0.1:0" : config.address(),
                                 {&service}, summary);
}
