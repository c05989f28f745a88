#include "stage/common/stage_locator.h"

#include <cstdlib>

#include "absl/strings/str_cat.h"
#include "stage/common/file_util.h"
#include "stage/common/proto_json.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"

namespace stage {
namespace {

bool EnvSet(const char* name) {
  const char* v = std::getenv(name);
  return v != nullptr && *v != '\0';
}

}  // namespace

absl::StatusOr<v1::SimEndpoints> ReadSimEndpoints(const StageLocator& where, const std::string& wanted) {
  std::string path = where.endpoints;
  if (path.empty())
    path = EnvSet("FASTAGE_ENDPOINTS") ? std::getenv("FASTAGE_ENDPOINTS") : DefaultSimRunDir() + "/endpoints.json";
  auto text = ReadFileToString(path);
  if (!text.ok()) {
    return absl::NotFoundError(absl::StrCat("no ", wanted, " (no stage-sim endpoint file at ", path, ")"));
  }
  v1::SimEndpoints endpoints;
  if (absl::Status s = FromContractJson(*text, &endpoints); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a stage-sim endpoint file: ", s.message()));
  }
  return endpoints;
}

absl::StatusOr<std::string> ResolveController(const StageLocator& where) {
  if (!where.controller.empty()) return where.controller;
  if (!where.rig_path.empty()) {
    auto loaded = LoadRig(where.rig_path);
    if (!loaded.ok()) return loaded.status();
    return loaded->rig.controller().listen();
  }
  if (EnvSet("FASTAGE_CONTROLLER")) return std::string(std::getenv("FASTAGE_CONTROLLER"));
  auto endpoints =
      ReadSimEndpoints(where, "controller address: pass --controller HOST:PORT or --config RIG, or start stage-sim");
  if (!endpoints.ok()) return endpoints.status();
  if (endpoints->controller().empty()) return absl::InvalidArgumentError("the endpoint file has no controller address");
  return endpoints->controller();
}

absl::Status UseStageSecurity(StageLocator* where, const std::string& default_identity) {
  // The rig of the stage ResolveController finds: --config, else (without --controller or $FASTAGE_CONTROLLER) the
  // endpoint file's.
  std::string rig_path = where->rig_path;
  if (rig_path.empty() && where->controller.empty() && !EnvSet("FASTAGE_CONTROLLER")) {
    auto endpoints = ReadSimEndpoints(*where, "endpoint file");
    if (endpoints.ok()) rig_path = endpoints->rig_file();
  }
  if (rig_path.empty()) {
    if (!where->identity.empty()) {
      return absl::InvalidArgumentError(
          "--as: no rig to read the stage's security from (pass --config RIG, or use a stage-sim endpoint file)");
    }
    return absl::OkStatus();
  }
  auto loaded = LoadRig(rig_path);
  if (!loaded.ok()) return loaded.status();
  if (loaded->rig.security().transport() != v1::TRANSPORT_MODE_MUTUAL_TLS) return absl::OkStatus();
  if (where->identity.empty()) {
    where->identity = EnvSet("FASTAGE_IDENTITY") ? std::getenv("FASTAGE_IDENTITY") : default_identity;
  }
  return UseRigTransportSecurity(*loaded, where->identity);
}

}  // namespace stage
