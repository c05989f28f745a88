// Suites that need addresses of their own (a GigE Vision camera per address) run in a network namespace they create:
// nothing they do reaches the host's network, and any number of them may run side by side.
#pragma once

#include <sched.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <string>

namespace stage::testing {

// Moves this process into a new network namespace with its loopback up and 127.0.0.first .. 127.0.0.last on it.
// Call from main() before any thread starts (unshare applies to the calling thread). Returns "" on success, or why
// it could not (the suite's tests then skip with it).
inline std::string IsolateNetwork(int first, int last) {
  if (unshare(CLONE_NEWNET) != 0) return std::string("unshare(CLONE_NEWNET): ") + std::strerror(errno) + " (needs root)";
  std::string script = "ip link set lo up";
  for (int n = first; n <= last; ++n) script += " && ip addr add 127.0.0." + std::to_string(n) + "/8 dev lo";
  if (std::system(script.c_str()) != 0) return "could not set up the namespace's loopback with ip(8)";
  return "";
}

}  // namespace stage::testing

namespace stage::testing {

// Hosts of a stage made by a test: `count` named network namespaces (ip netns add), each joined by a veth link to a
// bridge in the calling process's own namespace (IsolateNetwork first) at 10.77.0.1/24; host i (from 1) is
// 10.77.0.(10 + i) on its eth0. The namespaces are deleted on destruction; the bridge goes with the test's namespace.
class TestHosts {
 public:
  explicit TestHosts(int count) {
    prefix_ = "fastage-" + std::to_string(getpid()) + "-h";
    std::string script = "ip link add fastage-br type bridge && ip addr add 10.77.0.1/24 dev fastage-br && "
                         "ip link set fastage-br up";
    for (int i = 1; i <= count; ++i) {
      const std::string ns = Name(i), veth = "fastage-v" + std::to_string(i);
      script += " && ip netns add " + ns + " && ip link add " + veth + " type veth peer name eth0 netns " + ns +
                " && ip link set " + veth + " master fastage-br up && ip netns exec " + ns +
                " sh -c 'ip link set lo up && ip addr add " + Address(i) + "/24 dev eth0 && ip link set eth0 up'";
      made_ = i;
    }
    if (std::system(script.c_str()) != 0) why_not_ = "could not make the hosts' namespaces with ip(8): " + script;
  }
  ~TestHosts() {
    for (int i = 1; i <= made_; ++i) std::system(("ip netns del " + Name(i) + " 2>/dev/null").c_str());
  }
  TestHosts(const TestHosts&) = delete;
  TestHosts& operator=(const TestHosts&) = delete;

  // "" when the hosts are up, else why not.
  const std::string& why_not() const { return why_not_; }
  std::string Name(int i) const { return prefix_ + std::to_string(i); }
  static std::string Address(int i) { return "10.77.0." + std::to_string(10 + i); }
  static std::string Hub() { return "10.77.0.1"; }

 private:
  std::string prefix_;
  std::string why_not_;
  int made_ = 0;
};

}  // namespace stage::testing
