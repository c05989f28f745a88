// Child processes: fork/exec with PR_SET_PDEATHSIG, reaped by pid.
#include "stage/common/subprocess.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <map>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "stage/common/status.h"

extern char** environ;

namespace stage {
namespace {

ExitInfo FromWaitStatus(int status) {
  ExitInfo info;
  if (WIFSIGNALED(status)) {
    info.signal = WTERMSIG(status);
  } else if (WIFEXITED(status)) {
    info.exit_code = WEXITSTATUS(status);
  }
  return info;
}

bool IsExecutableFile(const std::string& path) {
  struct stat st;
  return stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode) && access(path.c_str(), X_OK) == 0;
}

}  // namespace

std::string ExitInfo::Describe() const {
  if (signal != 0) return absl::StrCat("killed by signal ", signal, " (", strsignal(signal), ")");
  return absl::StrCat("exit code ", exit_code);
}

absl::StatusOr<std::string> FindExecutable(const std::string& name) {
  if (name.empty()) return absl::InvalidArgumentError("empty program name");
  if (name.find('/') != std::string::npos) {
    if (IsExecutableFile(name)) return name;
    return absl::NotFoundError(absl::StrCat(name, ": no such executable file"));
  }
  const char* path = std::getenv("PATH");
  for (absl::string_view dir : absl::StrSplit(path ? path : "/usr/bin:/bin", ':', absl::SkipEmpty())) {
    std::string candidate = absl::StrCat(dir, "/", name);
    if (IsExecutableFile(candidate)) return candidate;
  }
  return absl::NotFoundError(absl::StrCat(name, ": not found in PATH"));
}

absl::StatusOr<std::unique_ptr<Subprocess>> Subprocess::Spawn(const SubprocessOptions& options) {
  if (options.argv.empty()) return absl::InvalidArgumentError("Subprocess: empty argv");
  STAGE_ASSIGN_OR_RETURN(std::string program, FindExecutable(options.argv[0]));

  // Everything the child needs is prepared before fork(): after it, only async-signal-safe calls.
  std::vector<char*> argv;
  for (const std::string& a : options.argv) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  std::map<std::string, std::string> env_map;
  for (char** e = environ; *e != nullptr; ++e) {
    absl::string_view entry(*e);
    env_map[std::string(entry.substr(0, entry.find('=')))] = std::string(entry);
  }
  for (const std::string& e : options.env) env_map[e.substr(0, e.find('='))] = e;
  std::vector<std::string> env_storage;
  for (auto& [name, entry] : env_map) env_storage.push_back(entry);
  std::vector<char*> envp;
  for (std::string& e : env_storage) envp.push_back(e.data());
  envp.push_back(nullptr);

  const int mode = options.append ? O_APPEND : O_TRUNC;
  auto open_out = [mode](const std::string& path) -> absl::StatusOr<int> {
    if (path.empty()) return -1;
    int fd = open(path.c_str(), O_WRONLY | O_CREAT | mode | O_CLOEXEC, 0644);
    if (fd < 0) return ErrnoToStatus(errno, absl::StrCat("cannot open ", path));
    return fd;
  };
  STAGE_ASSIGN_OR_RETURN(int out_fd, open_out(options.stdout_path));
  absl::StatusOr<int> err_fd_or = open_out(options.stderr_path);
  if (!err_fd_or.ok()) {
    if (out_fd >= 0) close(out_fd);
    return err_fd_or.status();
  }
  int err_fd = *err_fd_or;
  int in_fd = options.null_stdin ? open("/dev/null", O_RDONLY | O_CLOEXEC) : -1;
  const pid_t parent = getpid();

  pid_t pid = fork();
  if (pid < 0) {
    int err = errno;
    for (int fd : {out_fd, err_fd, in_fd}) {
      if (fd >= 0) close(fd);
    }
    return ErrnoToStatus(err, "fork");
  }
  if (pid == 0) {
    if (options.kill_with_parent) {
      prctl(PR_SET_PDEATHSIG, SIGKILL);
      if (getppid() != parent) _exit(127);  // the parent died before prctl took effect
    }
    // The parent blocks its shutdown signals and ignores SIGPIPE; exec keeps both, so reset them.
    sigset_t none;
    sigemptyset(&none);
    sigprocmask(SIG_SETMASK, &none, nullptr);
    signal(SIGPIPE, SIG_DFL);
    if (in_fd >= 0) dup2(in_fd, STDIN_FILENO);
    if (out_fd >= 0) dup2(out_fd, STDOUT_FILENO);
    if (err_fd >= 0) dup2(err_fd, STDERR_FILENO);
    execve(program.c_str(), argv.data(), envp.data());
    _exit(127);
  }
  for (int fd : {out_fd, err_fd, in_fd}) {
    if (fd >= 0) close(fd);
  }
  return std::unique_ptr<Subprocess>(new Subprocess(pid, program));
}

Subprocess::~Subprocess() {
  if (!exit_) {
    kill(pid_, SIGKILL);
    Wait();
  }
}

std::optional<ExitInfo> Subprocess::Poll() {
  if (exit_) return exit_;
  int status;
  pid_t r = waitpid(pid_, &status, WNOHANG);
  if (r == pid_) {
    exit_ = FromWaitStatus(status);
  } else if (r < 0 && errno == ECHILD) {
    exit_ = ExitInfo{-1, 0};  // reaped elsewhere; nothing left to wait for
  }
  return exit_;
}

std::optional<ExitInfo> Subprocess::Wait(std::optional<std::chrono::milliseconds> timeout) {
  if (exit_) return exit_;
  if (!timeout) {
    int status;
    pid_t r;
    do {
      r = waitpid(pid_, &status, 0);
    } while (r < 0 && errno == EINTR);
    exit_ = r == pid_ ? FromWaitStatus(status) : ExitInfo{-1, 0};
    return exit_;
  }
  auto deadline = std::chrono::steady_clock::now() + *timeout;
  while (true) {
    if (Poll()) return exit_;
    if (std::chrono::steady_clock::now() >= deadline) return std::nullopt;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
}

void Subprocess::Signal(int sig) {
  if (!exit_) kill(pid_, sig);
}

ExitInfo Subprocess::Terminate(std::chrono::milliseconds grace, bool* killed) {
  if (killed != nullptr) *killed = false;
  if (exit_) return *exit_;
  Signal(SIGTERM);
  if (auto info = Wait(grace)) return *info;
  if (killed != nullptr) *killed = true;
  Signal(SIGKILL);
  return *Wait();
}

}  // namespace stage
