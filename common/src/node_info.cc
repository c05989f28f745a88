// NodeInfo for GetInfo.
#include "stage/common/node_info.h"

#include <unistd.h>

#include <chrono>

#include "stage/common/version.h"

namespace stage {
namespace {

// Taken during static initialization: close enough to process start for an uptime display.
const auto g_process_start = std::chrono::steady_clock::now();

}  // namespace

std::string HostName() {
  char buffer[256] = {};
  if (gethostname(buffer, sizeof(buffer) - 1) != 0) return "";
  return buffer;
}

v1::NodeInfo MakeNodeInfo(const std::string& id, v1::NodeKind kind, v1::CameraRole role, const std::string& backend,
                          const std::string& rig_hash) {
  v1::NodeInfo info;
  info.set_id(id);
  info.set_kind(kind);
  info.set_camera_role(role);
  info.set_version(std::string(kVersion));
  info.set_backend(backend);
  info.set_uptime_ns(
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - g_process_start).count());
  info.set_pid(static_cast<int32_t>(getpid()));
  static const std::string host = HostName();
  info.set_hostname(host);
  info.set_rig_hash(rig_hash);
  return info;
}

std::string NodeKindName(v1::NodeKind kind) {
  switch (kind) {
    case v1::NODE_KIND_CONTROLLER:
      return "controller";
    case v1::NODE_KIND_CAMERA:
      return "camera";
    case v1::NODE_KIND_LIGHT:
      return "light";
    case v1::NODE_KIND_PROCESSING_WORKER:
      return "processing-worker";
    default:
      return "unknown";
  }
}

std::string NodeStateName(v1::NodeState state) {
  switch (state) {
    case v1::NODE_STATE_UP:
      return "up";
    case v1::NODE_STATE_DOWN:
      return "down";
    case v1::NODE_STATE_UNREACHABLE:
      return "unreachable";
    default:
      return "unknown";
  }
}

}  // namespace stage
