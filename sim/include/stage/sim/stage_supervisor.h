// Brings a whole simulated stage up on this machine and down again: one camera-node per camera, one light-node per
// light node, one processing-worker per worker, then stage-controller, all on loopback with ports the kernel picks.
// Children are tied to the supervisor's life (PR_SET_PDEATHSIG), ended by pid with SIGTERM and, after a grace
// period, SIGKILL, and always reaped: no orphans, even when a child hangs.
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "stage/common/rig.h"
#include "stage/common/subprocess.h"
#include "stage/v1/sim.pb.h"

namespace stage::sim {

struct StageSupervisorOptions {
  // Rig file, or "builtin:fastage".
  std::string rig = "builtin:fastage";
  // Directory for the endpoint file, the effective rig, the children's logs and port files.
  std::string run_dir;
  // Where camera-node, light-node, processing-worker and stage-controller are.
  std::string bin_dir;
  // How long the stage may take to come up (every node serving and seen up by the controller).
  std::chrono::milliseconds startup_timeout{60000};
  // Time children get between SIGTERM and SIGKILL.
  std::chrono::milliseconds grace{3000};
  // --log-level passed to every child.
  std::string child_log_level;
  // Rig field overrides (PATH=VALUE, as stagectl --set takes them), for every node.
  std::vector<std::string> overrides;
  // Where the controller listens; port 0 picks a free one.
  std::string controller_listen = "127.0.0.1:0";
  // The simulated world's SimWorld service (host:port), passed to every camera and light node as --sim-world; empty:
  // nodes run without a world (test-pattern cameras, lights that light nothing).
  std::string world_address;
  // The world runs from slot 0 without takes (stage-sim --world-slots): light nodes arm their tables themselves.
  // Otherwise the controller arms them for each take it runs on the world.
  bool self_armed_world = false;
  // Where the controller records takes (--take-root); empty: the rig's storage.root against the working directory.
  std::string take_root;
  // Every child serves Prometheus metrics on a loopback port it picks (--metrics-listen 127.0.0.1:0); the endpoint
  // file lists each one's (SimProcess.metrics).
  bool metrics = false;
  // stage-sim's own metrics endpoint (host:port), for the endpoint file; empty when it serves none.
  std::string own_metrics;
  // Where a node runs (stage-sim --place): in a network namespace of this machine (ip netns exec), listening on its
  // address there: hosts of a stage a test makes. Keyed by node id, or by kind ("camera", "light", "worker",
  // "controller"; an id's placement comes first). Unplaced nodes run in stage-sim's namespace on 127.0.0.1.
  struct Placement {
    std::string netns;  // a name under /run/netns
    std::string host;   // the node's address in it
  };
  std::map<std::string, Placement> placements;

  absl::Status Validate() const;
};

class StageSupervisor {
 public:
  explicit StageSupervisor(StageSupervisorOptions options);
  // Stops whatever is still running.
  ~StageSupervisor();

  // Starts every node, then the controller; waits until the controller sees every node up; writes the endpoint
  // file. On failure everything started so far is stopped, and the error names the process and its log.
  absl::Status Start();

  // Reaps children that exited since the last call and returns a line for each ("camera-node mv-03 (pid 123)
  // exited: killed by signal 9 (Killed); log: ...").
  std::vector<std::string> ReapExited();

  // SIGTERM to every child, SIGKILL after the grace period to those still there, reap all, remove the endpoint file.
  // Returns how many needed SIGKILL.
  int Stop();

  const v1::SimEndpoints& endpoints() const { return endpoints_; }
  std::string endpoints_path() const { return options_.run_dir + "/endpoints.json"; }
  const LoadedRig& rig() const { return rig_; }

 private:
  struct Child {
    std::string id;
    v1::NodeKind kind;
    std::string program;
    std::string port_file;
    std::string metrics_file;
    std::string log_file;
    std::string address;
    std::string metrics;
    std::unique_ptr<Subprocess> process;
    bool reported = false;
  };

  absl::Status PrepareRunDir();
  absl::Status SpawnChild(const std::string& program, const std::string& id, v1::NodeKind kind,
                          const std::string& config, const std::string& listen, std::vector<std::string> extra_args);
  absl::Status WaitForAddresses(std::chrono::steady_clock::time_point deadline);
  absl::Status WaitForStageUp(std::chrono::steady_clock::time_point deadline);
  absl::Status WriteEffectiveRig(const std::string& path, bool with_addresses = true);
  absl::Status WriteEndpoints();
  // The placement of node `id` of `kind`, or nullptr (options_.placements).
  const StageSupervisorOptions::Placement* PlacementOf(const std::string& id, v1::NodeKind kind) const;
  std::string DescribeExit(const Child& child) const;

  StageSupervisorOptions options_;
  LoadedRig rig_;
  std::vector<Child> children_;  // nodes first, the controller last
  v1::SimEndpoints endpoints_;
  bool started_ = false;
};

// The last non-empty line of a text file ("" if none), to quote a child's last words.
std::string LastLineOf(const std::string& path);

}  // namespace stage::sim
