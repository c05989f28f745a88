// camera-node: serves one camera of the stage (the CameraNode gRPC service) with the backend the rig names.
#include "backends.h"
#include "camera_node.h"
#include "camera_service.h"
#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/shutdown.h"

int main(int argc, char** argv) {
  stage::BlockShutdownSignals();
  CLI::App app{"Serves one camera of the FaStage rig (CameraNode gRPC service and grpc.health.v1).", "camera-node"};
  stage::CommonFlags flags;
  std::string id;
  std::string backend;
  stage::AddCommonFlags(app, &flags, /*serves=*/true);
  app.add_option("--id", id, "Id of this camera in the rig file")->required();
  app.add_option("--backend", backend, "Use this backend instead of the rig's (sim, aravis)");
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  const char* kProgram = "camera-node";
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  auto loaded = stage::LoadRig(flags.config);
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  auto camera = stage::FindCamera(*loaded, id);
  if (!camera.ok()) return stage::ReportFatal(kProgram, camera.status());
  const stage::v1::CameraConfig& config = **camera;
  if (backend.empty()) backend = config.backend();

  stage::RealClock clock(stage::RealClock::Kind::kRealtime);
  auto device = stage::camera::CreateCameraDevice(backend, config, &clock);
  if (!device.ok()) return stage::ReportFatal(kProgram, device.status());
  auto node = stage::camera::CameraNode::Create(config, std::move(*device), stage::RigHash(loaded->rig));
  if (!node.ok()) return stage::ReportFatal(kProgram, node.status());
  std::string summary = fmt::format("camera {}: {}, {}x{} {} at {} fps, exposure {} us, backend {}, rig {}",
                                    config.id(), (*node)->Info().role(), config.width(), config.height(),
                                    stage::PixelFormatName(config.pixel_format()), config.frame_rate_hz(),
                                    config.exposure_us(), backend, loaded->source_name);

  stage::camera::CameraService service(node->get());
  return stage::ServeUntilSignal(kProgram, flags, config.address().empty() ? "127.0.0.1:0" : config.address(),
                                 {&service}, summary);
}
