// stagectl: the command-line console of the stage (a thin StageController client).
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <iostream>

#include "absl/strings/str_cat.h"
#include "stage/common/cli.h"
#include "stage/common/file_util.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/common/version.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/sim.pb.h"
#include "status_format.h"

namespace {

constexpr const char* kProgram = "stagectl";

// Where the controller is: --controller, the rig's controller.listen (--config), $FASTAGE_CONTROLLER, the endpoint
// file (--endpoints, $FASTAGE_ENDPOINTS, or stage-sim's default run directory), in that order.
absl::StatusOr<std::string> ResolveController(const std::string& flag, const std::string& rig_path,
                                              const std::string& endpoints_flag) {
  if (!flag.empty()) return flag;
  if (!rig_path.empty()) {
    auto loaded = stage::LoadRig(rig_path);
    if (!loaded.ok()) return loaded.status();
    return loaded->rig.controller().listen();
  }
  if (const char* env = std::getenv("FASTAGE_CONTROLLER"); env != nullptr && *env != '\0') return std::string(env);
  std::string path = endpoints_flag;
  if (path.empty()) {
    const char* env = std::getenv("FASTAGE_ENDPOINTS");
    path = env != nullptr && *env != '\0' ? env : stage::DefaultSimRunDir() + "/endpoints.json";
  }
  auto text = stage::ReadFileToString(path);
  if (!text.ok()) {
    return absl::NotFoundError(absl::StrCat(
        "no controller address: pass --controller HOST:PORT or --config RIG, or start stage-sim (no endpoint file at ",
        path, ")"));
  }
  stage::v1::SimEndpoints endpoints;
  google::protobuf::util::JsonParseOptions options;
  options.ignore_unknown_fields = true;
  if (auto s = google::protobuf::util::JsonStringToMessage(*text, &endpoints, options); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a stage-sim endpoint file: ", s.message().as_string()));
  }
  if (endpoints.controller().empty()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": has no controller address"));
  }
  return endpoints.controller();
}

int Status(const std::string& address, int timeout_ms, bool json) {
  auto channel = grpc::CreateChannel(address, grpc::InsecureChannelCredentials());
  auto stub = stage::v1::StageController::NewStub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(timeout_ms));
  stage::v1::StageStatus status;
  grpc::Status rpc = stub->GetStageStatus(&context, stage::v1::GetStageStatusRequest(), &status);
  if (!rpc.ok()) {
    return stage::ReportFatal(kProgram,
                              stage::Annotate(stage::FromGrpcStatus(rpc), absl::StrCat("controller at ", address)));
  }
  if (json) {
    std::cout << stage::stagectl::StatusToJson(status) << "\n";
  } else {
    int64_t now =
        std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch())
            .count();
    std::cout << stage::stagectl::FormatStatusTable(status, now, isatty(STDOUT_FILENO) != 0);
  }
  return status.nodes_up() == status.nodes_total() ? 0 : 3;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Command-line console of the FaStage stage. Exit codes: 0 ok, 1 failure, 2 bad usage, "
      "3 status shows nodes that are not up.",
      "stagectl"};
  app.set_version_flag("--version", std::string("stagectl (FaStage) ") + std::string(stage::kVersion));
  std::string controller;
  std::string endpoints;
  std::string rig_path;
  std::string log_level;
  int timeout_ms = 3000;
  app.add_option("--controller", controller,
                 "Controller address host:port (default: $FASTAGE_CONTROLLER or the "
                 "stage-sim endpoint file)");
  app.add_option("--config", rig_path, "Rig file: talk to the controller at its controller.listen address");
  app.add_option(
      "--endpoints", endpoints,
      "stage-sim endpoint file (default: $FASTAGE_ENDPOINTS or " + stage::DefaultSimRunDir() + "/endpoints.json)");
  app.add_option("--timeout-ms", timeout_ms, "Deadline of each call to the controller")->check(CLI::Range(1, 600000));
  app.add_option("--log-level", log_level, "Log levels (spdlog syntax)");
  app.require_subcommand(1);
  bool json = false;
  CLI::App* status = app.add_subcommand("status", "Show every node of the stage: state, address, version, RTT");
  status->add_flag("--json", json, "Print JSON for scripts instead of the table");
  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  if (auto s = stage::InitLogging(kProgram, log_level); !s.ok()) return stage::ReportFatal(kProgram, s);

  auto address = ResolveController(controller, rig_path, endpoints);
  if (!address.ok()) return stage::ReportFatal(kProgram, address.status());
  if (status->parsed()) return Status(*address, timeout_ms, json);
  return 2;
}
