// Child processes for supervisors (stage-sim) and tests: spawn with arguments, environment and redirected output,
// tied to the parent's life, and ended by pid (SIGTERM, then SIGKILL after a grace period), always reaped.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace stage {

struct SubprocessOptions {
  // argv[0] is the program: a path, or a name looked up in PATH.
  std::vector<std::string> argv;
  // Extra environment entries "NAME=value", added to (and overriding) the parent's environment.
  std::vector<std::string> env;
  // Files to send the child's stdout / stderr to (created or truncated); empty = inherit the parent's.
  std::string stdout_path;
  std::string stderr_path;
  // Append to those files instead of truncating them (one file for both then holds both streams in order).
  bool append = false;
  // stdin from /dev/null (the default) rather than the parent's.
  bool null_stdin = true;
  // The kernel sends SIGKILL to the child when the parent thread that spawned it exits (PR_SET_PDEATHSIG), so a
  // supervisor that dies, even by SIGKILL, leaves no orphan. Spawn from a thread that lives as long as the child.
  bool kill_with_parent = true;
};

// How a child ended.
struct ExitInfo {
  int exit_code = 0;  // valid when signal == 0
  int signal = 0;     // the signal that killed it, or 0
  bool ok() const { return signal == 0 && exit_code == 0; }
  // "exit code 3", "killed by signal 9 (Killed)".
  std::string Describe() const;
};

class Subprocess {
 public:
  // Starts the child. Errors (program not found, not executable) are reported here, not as a mysterious exit 127.
  static absl::StatusOr<std::unique_ptr<Subprocess>> Spawn(const SubprocessOptions& options);

  // Kills (SIGKILL) and reaps the child if it is still running: a Subprocess never leaks a process.
  ~Subprocess();

  pid_t pid() const { return pid_; }
  const std::string& program() const { return program_; }

  // Reaps the child if it has exited; nullopt while it runs. Never blocks.
  std::optional<ExitInfo> Poll();
  // Waits for the child to exit, at most `timeout` (forever if nullopt). Nullopt on timeout.
  std::optional<ExitInfo> Wait(std::optional<std::chrono::milliseconds> timeout = std::nullopt);
  // Sends `sig` if the child has not been reaped yet.
  void Signal(int sig);
  // SIGTERM, wait up to `grace`, then SIGKILL and reap. Returns how it ended and whether SIGKILL was needed.
  ExitInfo Terminate(std::chrono::milliseconds grace, bool* killed = nullptr);

  bool exited() const { return exit_.has_value(); }
  const std::optional<ExitInfo>& exit_info() const { return exit_; }

 private:
  Subprocess(pid_t pid, std::string program) : pid_(pid), program_(std::move(program)) {}
  pid_t pid_;
  std::string program_;
  std::optional<ExitInfo> exit_;
};

// Finds `name` in PATH (or checks it as a path when it contains '/'); NotFound naming it otherwise.
absl::StatusOr<std::string> FindExecutable(const std::string& name);

}  // namespace stage
