// The rig's transport security (rig_security.h).
#include "stage/common/rig_security.h"

#include <filesystem>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "stage/common/logging.h"
#include "stage/common/status.h"

namespace stage {

TransportSecurity RigTransportSecurity(const LoadedRig& rig, absl::string_view identity) {
  const v1::SecurityConfig& config = rig.rig.security();
  TransportSecurity security;
  security.reload_interval_s = static_cast<int>(config.reload_interval_s() > 0 ? config.reload_interval_s() : 5);
  if (config.transport() != v1::TRANSPORT_MODE_MUTUAL_TLS) return security;
  auto resolve = [&](const std::string& path) {
    const std::filesystem::path p(path);
    return (p.is_relative() ? std::filesystem::path(rig.base_dir) / p : p).lexically_normal().string();
  };
  const std::string dir = resolve(config.cert_dir());
  const std::string name = absl::StrReplaceAll(identity, {{"/", "-"}});
  security.mode = TransportSecurity::Mode::kMutualTls;
  security.ca_file = resolve(config.ca_file());
  security.cert_file = absl::StrCat(dir, "/", name, ".crt");
  security.key_file = absl::StrCat(dir, "/", name, ".key");
  return security;
}

absl::Status UseRigTransportSecurity(const LoadedRig& rig, absl::string_view identity) {
  STAGE_RETURN_IF_ERROR(Annotate(SetTransportSecurity(RigTransportSecurity(rig, identity)),
                                 absl::StrCat(rig.source_name, ": security (as ", identity, ")")));
  // Plain text is said where a server starts ("serving on ADDRESS (plain text, loopback only)").
  if (ProcessTransportSecurity().mode != TransportSecurity::Mode::kPlainText) {
    Logger("rpc")->info("transport: {}", DescribeTransportSecurity());
  }
  return absl::OkStatus();
}

}  // namespace stage
