// processing-worker: runs processing stages on frame sets (the ProcessingWorker gRPC service).
#include <thread>

#include "stage/common/cli.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"
#include "stage/common/shutdown.h"
#include "worker_service.h"

int main(int argc, char** argv) {
  stage::ExecWithPassiveOpenMp(argv);  // torch's and Open3D's OpenMP loops
  stage::BlockShutdownSignals();
  CLI::App app{"Serves a FaStage processing worker (ProcessingWorker gRPC service and grpc.health.v1).",
               "processing-worker"};
  stage::CommonFlags flags;
  std::string id;
  stage::AddCommonFlags(app, &flags, /*serves=*/true);
  app.add_option("--id", id, "Id of this worker in the rig file")->required();
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  const char* kProgram = "processing-worker";
  if (auto s = stage::InitLogging(kProgram, flags.log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  auto loaded = stage::LoadRig(flags.config);
  if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
  if (auto s = stage::UseRigTransportSecurity(*loaded, "worker/" + id); !s.ok()) return stage::ReportFatal(kProgram, s);
  auto entry = stage::FindProcessingWorker(*loaded, id);
  if (!entry.ok()) return stage::ReportFatal(kProgram, entry.status());
  const stage::v1::ProcessingWorkerConfig& config = **entry;
  uint32_t threads = config.threads() > 0 ? config.threads() : std::max(1u, std::thread::hardware_concurrency());
  std::string summary =
      fmt::format("processing worker {}: {} threads, rig {}", config.id(), threads, loaded->source_name);

  stage::processing::WorkerService service(config.id(), stage::RigHash(loaded->rig), threads);
  return stage::ServeUntilSignal(kProgram, flags, config.address().empty() ? "127.0.0.1:0" : config.address(),
                                 {&service}, summary);
}
