// Polls every node's grpc.health.v1 service on its own thread and keeps each node's state (up, down,
// unreachable) with the reason, round trip and last GetInfo; and, while a node is up, measures its clock against the
// controller's (bursts of NodeClock.Sync, filtered and fitted by timing::ClockEstimator) and flags it when the
// uncertainty is more than its trigger mode tolerates. A node that hangs delays only its own poller.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "stage/v1/node.pb.h"

namespace stage::controller {

struct NodeTarget {
  std::string id;
  v1::NodeKind kind = v1::NODE_KIND_UNSPECIFIED;
  v1::CameraRole role = v1::CAMERA_ROLE_UNSPECIFIED;  // cameras' only
  std::string address;
  // The largest clock uncertainty the node's trigger mode tolerates (0 = no requirement), and why.
  int64_t clock_limit_ns = 0;
  std::string clock_limit_reason;
  // The node cannot work without a measurement (scheduled software triggers): unmeasured, it is flagged.
  bool clock_required = false;
};

struct HealthMonitorOptions {
  // Time between the starts of two polls of one node.
  std::chrono::milliseconds poll_interval{200};
  // Deadline of one poll; no answer by then means "unreachable".
  std::chrono::milliseconds timeout{500};
  // Time between clock measurements of a node that is up; 0 = no clock measurements.
  std::chrono::milliseconds clock_sync_interval{1000};
  // NodeClock.Sync exchanges per measurement.
  int clock_sync_burst = 8;
};

class HealthMonitor {
 public:
  HealthMonitor(std::vector<NodeTarget> targets, HealthMonitorOptions options);
  // Stops polling.
  ~HealthMonitor();

  // Starts one poller thread per node. Call once.
  void Start();
  // Stops and joins the pollers; wakes watchers. Idempotent.
  void Stop();

  // Every node in target order.
  std::vector<v1::NodeStatus> Snapshot() const;

  // A counter that grows whenever a node's state, reason or version changes.
  uint64_t generation() const;
  // Waits until generation() != `seen`, Stop(), or `timeout`; returns generation().
  uint64_t WaitForChange(uint64_t seen, std::chrono::milliseconds timeout) const;
  // Something else the stage's status shows changed (the capture session's state): counts it and wakes watchers.
  void NotifyChange();

 private:
  struct Node;
  void Poll(size_t index);
  void SyncClock(Node& node);

  HealthMonitorOptions options_;
  std::vector<std::unique_ptr<Node>> nodes_;
  std::vector<std::thread> threads_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;  // watchers wait here
  std::condition_variable stop_;             // pollers wait here between polls
  uint64_t generation_ = 0;                  // guarded by mutex_
  bool stopping_ = false;                    // guarded by mutex_
};

}  // namespace stage::controller
