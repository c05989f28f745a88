// The nodes of a take as the capture session reaches them: a camera node and a light node, each behind a small
// interface. The controller's are gRPC clients (GrpcNodeClients); the session's unit tests give it fakes, so a take is
// tested in one process, with no node and no simulator.
//
// Requests a node answers the same when asked twice (arming a take, its plan, disarming) take a `give_up` time: a node
// slow to answer on a loaded host is asked again until then, rather than counted out. Errors are the node's (its gRPC
// status as an absl::Status); Unavailable means the node refuses connections (its process is not there).
#pragma once

#include <chrono>
#include <functional>
#include <memory>

#include "absl/status/status.h"
#include "stage/v1/camera_node.pb.h"
#include "stage/v1/light_node.pb.h"
#include "stage/v1/rig.pb.h"

namespace stage::controller {

using SteadyTime = std::chrono::steady_clock::time_point;

class CameraClient {
 public:
  virtual ~CameraClient() = default;
  virtual absl::Status Arm(const v1::ArmCameraRequest& request, SteadyTime give_up, v1::ArmCameraResponse* reply) = 0;
  // The take's new plan (its length and gaps; T0 once it starts).
  virtual absl::Status UpdateTake(const v1::UpdateTakeRequest& request, SteadyTime give_up) = 0;
  // Its statistics now; a poll, with a short deadline.
  virtual absl::Status GetStats(v1::CameraStats* stats) = 0;
  virtual absl::Status GetPreview(const v1::GetPreviewRequest& request, v1::Preview* preview) = 0;
  // Finishes the take: the node drains (and offloads a burst) and reports every slot; may take minutes.
  virtual absl::Status Finish(const v1::FinishCameraRequest& request, std::chrono::milliseconds deadline,
                              v1::CameraTakeReport* report) = 0;
};

class LightClient {
 public:
  virtual ~LightClient() = default;
  virtual absl::Status Arm(const v1::ArmLightRequest& request, SteadyTime give_up, v1::LightStats* stats) = 0;
  virtual absl::Status Heartbeat(const v1::HeartbeatRequest& request, std::chrono::milliseconds deadline,
                                 v1::LightStats* stats) = 0;
  virtual absl::Status Disarm(const v1::DisarmLightRequest& request, SteadyTime give_up, v1::LightStats* stats) = 0;
  // The edge of the armed table's first row, on a clock that runs free.
  virtual absl::Status StartTable(const v1::StartTableRequest& request, SteadyTime give_up) = 0;
};

// How the session reaches the rig's nodes: one factory per kind.
struct NodeClients {
  std::function<std::unique_ptr<CameraClient>(const v1::CameraConfig&)> camera;
  std::function<std::unique_ptr<LightClient>(const v1::LightNodeConfig&)> light;
};

// gRPC clients of every node at its rig address; `answer` is the deadline of each try of a request asked patiently.
NodeClients GrpcNodeClients(std::chrono::milliseconds answer = std::chrono::seconds(10));

}  // namespace stage::controller
