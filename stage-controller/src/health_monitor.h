// Polls every node's grpc.health.v1 service on its own thread and keeps each node's state (up, down,
// unreachable) with the reason, round trip and last GetInfo. A node that hangs delays only its own poller.
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
  std::string role;
  std::string address;
};

struct HealthMonitorOptions {
  // Time between the starts of two polls of one node.
  std::chrono::milliseconds poll_interval{200};
  // Deadline of one poll; no answer by then means "unreachable".
  std::chrono::milliseconds timeout{500};
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

 private:
  struct Node;
  void Poll(size_t index);

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
