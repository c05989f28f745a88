// Synchronous signal handling.
#include "stage/common/shutdown.h"

#include <pthread.h>
#include <signal.h>

#include <cerrno>

namespace stage {
namespace {

sigset_t g_set;
bool g_have_sigchld = false;

}  // namespace

void BlockShutdownSignals(bool include_sigchld) {
  sigemptyset(&g_set);
  sigaddset(&g_set, SIGINT);
  sigaddset(&g_set, SIGTERM);
  if (include_sigchld) sigaddset(&g_set, SIGCHLD);
  g_have_sigchld = include_sigchld;
  pthread_sigmask(SIG_BLOCK, &g_set, nullptr);
  signal(SIGPIPE, SIG_IGN);
}

std::optional<int> WaitForShutdownSignal(std::optional<std::chrono::milliseconds> timeout) {
  while (true) {
    int sig;
    if (!timeout) {
      if (sigwait(&g_set, &sig) == 0) return sig;
      continue;
    }
    timespec ts;
    ts.tv_sec = timeout->count() / 1000;
    ts.tv_nsec = (timeout->count() % 1000) * 1000000;
    sig = sigtimedwait(&g_set, nullptr, &ts);
    if (sig > 0) return sig;
    if (errno == EAGAIN) return std::nullopt;
    // EINTR: another signal interrupted the wait; wait again.
  }
}

}  // namespace stage
