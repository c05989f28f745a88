// SIGINT/SIGTERM handling for every program: the signals are blocked in all threads (call BlockShutdownSignals()
// first thing in main, before any thread exists, so threads inherit the mask) and received synchronously by the
// thread that calls WaitForShutdownSignal(). No async-signal-safety puzzles, no lost signals.
#pragma once

#include <chrono>
#include <optional>

namespace stage {

// Blocks SIGINT, SIGTERM (and SIGCHLD when `include_sigchld`, for supervisors) in the calling thread; ignores
// SIGPIPE so a closed socket is an error return, not a death.
void BlockShutdownSignals(bool include_sigchld = false);

// Waits until SIGINT or SIGTERM arrives (returns its number), or `timeout` passes (returns nullopt). With
// `include_sigchld` set in BlockShutdownSignals, SIGCHLD is returned too.
std::optional<int> WaitForShutdownSignal(std::optional<std::chrono::milliseconds> timeout = std::nullopt);

}  // namespace stage
