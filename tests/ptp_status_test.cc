// A node reports the PTP state of its host beside the controller's own clock measurement: real linuxptp (ptp4l master
// and slave, software timestamping, over a veth pair between two network namespaces this test creates), read by the
// node through pmc, shown in the controller's status. Both ptp4l run free (free_running 1): they measure but never
// adjust this machine's clock. Needs root for the namespaces; skipped with a message otherwise.
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <thread>

#include "absl/strings/str_join.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "health_monitor.h"
#include "stage/common/subprocess.h"
#include "test_support.h"

namespace stage::testing {
namespace {

constexpr auto kCommandTimeout = std::chrono::seconds(10);

class PtpNamespaces : public ::testing::Test {
 protected:
  void SetUp() override {
    if (geteuid() != 0) GTEST_SKIP() << "needs root to create network namespaces (ip netns add)";
    for (const char* tool : {"ip", "ptp4l", "pmc"}) {
      if (!FindExecutable(tool).ok() && !FindExecutable(std::string("/usr/sbin/") + tool).ok()) {
        FAIL() << tool << " is missing: scripts/bootstrap installs iproute2 and linuxptp";
      }
    }
    const std::string tag = std::to_string(getpid());
    ns_a_ = "fastage-ptp-a-" + tag;
    ns_b_ = "fastage-ptp-b-" + tag;
    veth_a_ = "fpa" + tag;
    veth_b_ = "fpb" + tag;
    Ip({"netns", "add", ns_a_});
    Ip({"netns", "add", ns_b_});
    created_ = true;
    Ip({"link", "add", veth_a_, "type", "veth", "peer", "name", veth_b_});
    Ip({"link", "set", veth_a_, "netns", ns_a_});
    Ip({"link", "set", veth_b_, "netns", ns_b_});
    Ip({"-n", ns_a_, "addr", "add", "10.213.7.1/24", "dev", veth_a_});
    Ip({"-n", ns_b_, "addr", "add", "10.213.7.2/24", "dev", veth_b_});
    Ip({"-n", ns_a_, "link", "set", veth_a_, "up"});
    Ip({"-n", ns_b_, "link", "set", veth_b_, "up"});
  }

  void TearDown() override {
    for (auto& p : ptp4l_) p->Terminate(std::chrono::milliseconds(2000));
    ptp4l_.clear();
    if (created_) {
      RunCommand({"/usr/sbin/ip", "netns", "del", ns_a_}, kCommandTimeout);
      RunCommand({"/usr/sbin/ip", "netns", "del", ns_b_}, kCommandTimeout);
    }
  }

  void Ip(std::vector<std::string> args) {
    args.insert(args.begin(), FindExecutable("ip").ok() ? *FindExecutable("ip") : "/usr/sbin/ip");
    CommandResult r = RunCommand(args, kCommandTimeout);
    ASSERT_EQ(r.exit.exit_code, 0) << absl::StrJoin(args, " ") << ": " << r.err;
  }

  // ptp4l in `ns` on `iface`, its management socket at `uds`; fast announce and sync so that the test is short.
  void StartPtp4l(const std::string& ns, const std::string& iface, const std::string& uds, bool slave_only) {
    std::vector<std::string> argv = {"/usr/sbin/ip",
                                     "netns",
                                     "exec",
                                     ns,
                                     "ptp4l",
                                     "-S",
                                     "-i",
                                     iface,
                                     "-m",
                                     "--uds_address",
                                     uds,
                                     "--free_running",
                                     "1",
                                     "--logAnnounceInterval",
                                     "-2",
                                     "--logSyncInterval",
                                     "-3",
                                     "--announceReceiptTimeout",
                                     "2"};
    if (slave_only) argv.push_back("-s");
    auto p = Subprocess::Spawn(
        {.argv = argv, .stdout_path = dir_.path() + "/" + ns + ".log", .stderr_path = dir_.path() + "/" + ns + ".err"});
    ASSERT_TRUE(p.ok()) << p.status();
    ptp4l_.push_back(std::move(*p));
  }

  TempDir dir_;
  std::string ns_a_, ns_b_, veth_a_, veth_b_;
  bool created_ = false;
  std::vector<std::unique_ptr<Subprocess>> ptp4l_;
};

TEST_F(PtpNamespaces, NodeReportsPtp4lStateBesideTheClockMeasurement) {
  const std::string uds = dir_.path() + "/ptp4l-b";
  ASSERT_NO_FATAL_FAILURE(StartPtp4l(ns_a_, veth_a_, dir_.path() + "/ptp4l-a", /*slave_only=*/false));
  ASSERT_NO_FATAL_FAILURE(StartPtp4l(ns_b_, veth_b_, uds, /*slave_only=*/true));

  // A processing worker on loopback, reading the slave's state through its socket.
  const std::string port_file = dir_.path() + "/worker.port";
  auto worker = Subprocess::Spawn({.argv = {BinDir() + "/processing-worker", "--id", "worker-1", "--listen",
                                            "127.0.0.1:0", "--port-file", port_file, "--ptp-uds", uds},
                                   .stderr_path = dir_.path() + "/worker.log"});
  ASSERT_TRUE(worker.ok()) << worker.status();
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (!std::filesystem::exists(port_file) && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  ASSERT_TRUE(std::filesystem::exists(port_file)) << ReadFile(dir_.path() + "/worker.log");

  controller::HealthMonitor monitor(
      {{"worker-1", v1::NODE_KIND_PROCESSING_WORKER, v1::CAMERA_ROLE_UNSPECIFIED, ReadFile(port_file)}},
      {std::chrono::milliseconds(100), std::chrono::milliseconds(500), std::chrono::milliseconds(200), 4});
  monitor.Start();
  v1::ClockStatus clock;
  deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (std::chrono::steady_clock::now() < deadline) {
    clock = monitor.Snapshot()[0].clock();
    if (clock.ptp().grandmaster_present() && clock.ptp().port_state() != "LISTENING") break;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  monitor.Stop();
  (*worker)->Terminate(std::chrono::milliseconds(2000));
  EXPECT_TRUE(clock.measured());
  EXPECT_EQ(clock.ptp().source(), "linuxptp");
  EXPECT_TRUE(clock.ptp().error().empty()) << clock.ptp().error();
  EXPECT_TRUE(clock.ptp().grandmaster_present()) << "slave never saw the master; ptp4l logs:\n"
                                                 << ReadFile(dir_.path() + "/" + ns_b_ + ".log");
  EXPECT_THAT(clock.ptp().port_state(), ::testing::AnyOf("UNCALIBRATED", "SLAVE"));
  EXPECT_FALSE(clock.ptp().grandmaster_id().empty());
  EXPECT_EQ(clock.ptp().steps_removed(), 1);
}

}  // namespace
}  // namespace stage::testing
