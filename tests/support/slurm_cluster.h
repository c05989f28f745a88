// A single-node Slurm cluster for tests and benchmarks: Debian's slurmctld and slurmd in the foreground, a slurm.conf
// generated in a directory of the caller's (free loopback ports, AuthType=auth/none, proctrack/linuxproc, task/none,
// no accounting), both daemons ended by their pids.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "stage/common/subprocess.h"

namespace stage::testing {

class SlurmCluster {
 public:
  // Starts the cluster in `dir` (state, spool and logs under it), its node with `cpus` CPUs, and waits (up to
  // a minute) for the node to be idle. ok() says whether it came up; error() why not.
  explicit SlurmCluster(const std::string& dir, int cpus = 2);
  // Cancels what is left of its jobs, then ends both daemons by their pids.
  ~SlurmCluster();

  bool ok() const { return ok_; }
  const std::string& error() const { return error_; }
  // The environment Slurm's commands need to find it: {"SLURM_CONF=<dir>/slurm.conf"}.
  std::vector<std::string> env() const { return {"SLURM_CONF=" + conf_}; }
  const std::string& conf() const { return conf_; }
  const std::string& dir() const { return dir_; }
  // slurmctld's and slurmd's logs, for a failed test's message.
  std::string Logs() const;

 private:
  bool WaitForIdleNode();
  std::string dir_, conf_, error_;
  std::unique_ptr<Subprocess> controller_, node_;
  bool ok_ = false;
};

}  // namespace stage::testing
