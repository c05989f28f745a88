// Suites that need addresses of their own (a GigE Vision camera per address) run in a network namespace they create:
// nothing they do reaches the host's network, and any number of them may run side by side.
#pragma once

#include <sched.h>

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
