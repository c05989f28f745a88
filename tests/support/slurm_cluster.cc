#include "slurm_cluster.h"

#include <netinet/in.h>
#include <pwd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "stage/common/node_info.h"
#include "test_support.h"

namespace stage::testing {
namespace {

// A loopback TCP port nothing listens on now (bound, read, released).
int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t n = sizeof(a);
  int port = 0;
  if (bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof(a)) == 0 &&
      getsockname(fd, reinterpret_cast<sockaddr*>(&a), &n) == 0) {
    port = ntohs(a.sin_port);
  }
  close(fd);
  return port;
}

std::string UserName() {
  const passwd* pw = getpwuid(getuid());
  return pw != nullptr ? pw->pw_name : "root";
}

}  // namespace

SlurmCluster::SlurmCluster(const std::string& dir, int cpus) : dir_(dir), conf_(dir + "/slurm.conf") {
  for (const char* d : {"state", "spool", "logs"}) std::filesystem::create_directories(dir_ + "/" + d);
  const int controller_port = FreePort(), node_port = FreePort();
  const std::string host = stage::HostName(), user = UserName();
  std::ofstream(conf_) << "# A single-node cluster for FaStage's tests (tests/support/slurm_cluster.cc)\n"
                       << "ClusterName=fastage-test\n"
                       << "SlurmctldHost=" << host << "(127.0.0.1)\n"
                       << "SlurmctldPort=" << controller_port << "\n"
                       << "SlurmdPort=" << node_port << "\n"
                       << "SlurmUser=" << user << "\nSlurmdUser=" << user << "\n"
                       << "AuthType=auth/none\nCredType=cred/none\n"
                       << "ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n"
                       << "SchedulerType=sched/backfill\nSelectType=select/cons_tres\nSelectTypeParameters=CR_Core\n"
                       << "MpiDefault=none\nJobCompType=jobcomp/none\nJobAcctGatherType=jobacct_gather/none\n"
                       << "AccountingStorageType=accounting_storage/none\nReturnToService=2\n"
                       << "StateSaveLocation=" << dir_ << "/state\n"
                       << "SlurmdSpoolDir=" << dir_ << "/spool\n"
                       << "SlurmctldPidFile=" << dir_ << "/slurmctld.pid\n"
                       << "SlurmdPidFile=" << dir_ << "/slurmd.pid\n"
                       << "SlurmctldLogFile=" << dir_ << "/logs/slurmctld.log\n"
                       << "SlurmdLogFile=" << dir_ << "/logs/slurmd.log\n"
                       << "NodeName=fastage-node NodeHostname=" << host << " NodeAddr=127.0.0.1 CPUs=" << cpus
                       << " RealMemory=4000 State=UNKNOWN\n"
                       << "PartitionName=stage Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n";
  const std::vector<std::string> env = this->env();
  auto controller = Subprocess::Spawn({.argv = {"slurmctld", "-D", "-i", "-f", conf_},
                                       .env = env,
                                       .stdout_path = dir_ + "/logs/slurmctld.out",
                                       .stderr_path = dir_ + "/logs/slurmctld.out",
                                       .append = true});
  if (!controller.ok()) {
    error_ = std::string(controller.status().message());
    return;
  }
  controller_ = std::move(*controller);
  auto node = Subprocess::Spawn({.argv = {"slurmd", "-D", "-N", "fastage-node", "-f", conf_},
                                 .env = env,
                                 .stdout_path = dir_ + "/logs/slurmd.out",
                                 .stderr_path = dir_ + "/logs/slurmd.out",
                                 .append = true});
  if (!node.ok()) {
    error_ = std::string(node.status().message());
    return;
  }
  node_ = std::move(*node);
  ok_ = WaitForIdleNode();
}

bool SlurmCluster::WaitForIdleNode() {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  std::string last;
  while (std::chrono::steady_clock::now() < deadline) {
    if (controller_->Poll() || node_->Poll()) {
      error_ = "a Slurm daemon exited: " + Logs();
      return false;
    }
    CommandResult r = RunCommand({"/usr/bin/sinfo", "-h", "-N", "-o", "%t"}, std::chrono::seconds(10), env());
    last = r.out + r.err;
    if (r.exit.ok() && r.out.rfind("idle", 0) == 0) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  error_ = absl::StrCat("the node was not idle within 60 s (sinfo: ", last, "): ", Logs());
  return false;
}

std::string SlurmCluster::Logs() const {
  return absl::StrCat("slurmctld: ", ReadFile(dir_ + "/logs/slurmctld.out"),
                      "\nslurmd: ", ReadFile(dir_ + "/logs/slurmd.out"));
}

SlurmCluster::~SlurmCluster() {
  if (controller_ && node_ && ok_) {
    RunCommand({"/usr/bin/scancel", "--user", UserName()}, std::chrono::seconds(10), env());
    // The jobs' steps end before slurmd does, so that none outlives the cluster.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (std::chrono::steady_clock::now() < deadline) {
      CommandResult q =
          RunCommand({"/usr/bin/squeue", "-h", "-t", "running,completing"}, std::chrono::seconds(10), env());
      if (!q.exit.ok() || q.out.empty()) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
  }
  if (node_) node_->Terminate(std::chrono::seconds(10));
  if (controller_) controller_->Terminate(std::chrono::seconds(10));
}

}  // namespace stage::testing
