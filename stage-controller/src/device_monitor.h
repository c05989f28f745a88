// Reads every camera's and light node's device (its GetStats) once a second, each on its own thread, apart from the
// health monitor's link checks: what the console shows as a node's device state (a light node's mode, temperature
// and duty; a camera's link and frames) beside its link state. A node that hangs delays only its own reader.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "stage/v1/controller.pb.h"

namespace stage::controller {

struct DeviceTarget {
  std::string id;
  v1::NodeKind kind = v1::NODE_KIND_UNSPECIFIED;
  // Reads the device within `deadline` into `device`'s stats (camera or light).
  std::function<absl::Status(std::chrono::milliseconds deadline, v1::NodeDevice* device)> read;
};

struct DeviceMonitorOptions {
  // Time between the starts of two reads of one node.
  std::chrono::milliseconds interval{1000};
  // Deadline of one read.
  std::chrono::milliseconds timeout{500};

  // InvalidArgument naming the field when the interval or timeout is not positive.
  absl::Status Validate() const;
};

class DeviceMonitor {
 public:
  // `on_change` (may be empty) runs on a reader's thread when what a node's device shows as its state changes (a light
  // node's mode, a camera's link, a read that starts or stops failing): the stage's watchers wake for it.
  DeviceMonitor(std::vector<DeviceTarget> targets, DeviceMonitorOptions options, std::function<void()> on_change);
  ~DeviceMonitor();

  // Starts one reader thread per node. Call once.
  void Start();
  // Stops and joins the readers. Idempotent.
  void Stop();

  // Every node in target order: its last successful read (stats and time), and the error of the last read if it failed.
  std::vector<v1::NodeDevice> Snapshot() const;

 private:
  void Read(size_t index);

  std::vector<DeviceTarget> targets_;
  DeviceMonitorOptions options_;
  std::function<void()> on_change_;
  std::vector<std::thread> threads_;
  mutable std::mutex mutex_;
  std::condition_variable stop_;
  std::vector<v1::NodeDevice> devices_;  // guarded by mutex_
  bool stopping_ = false;                // guarded by mutex_
};

// The rig's cameras and light nodes, read over gRPC (CameraNode.GetStats, LightNode.GetStats) at their addresses.
std::vector<DeviceTarget> DeviceTargetsFromRig(const v1::RigConfig& rig);

}  // namespace stage::controller
