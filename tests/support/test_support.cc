// Helpers for cross-process suites.
#include "test_support.h"

#include <sys/stat.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <thread>

#include "stage/common/file_util.h"

namespace stage::testing {

std::string BinDir() {
  const char* dir = std::getenv("FASTAGE_BIN_DIR");
  return dir != nullptr ? dir : "build/bin";
}

std::string ReadFile(const std::string& path) { return ReadFileToString(path).value_or(""); }

std::map<std::string, std::string> FilesUnder(const std::string& root) {
  std::map<std::string, std::string> out;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(root)) {
    if (!entry.is_regular_file()) continue;
    out[std::filesystem::relative(entry.path(), root).string()] = ReadFile(entry.path().string());
  }
  return out;
}

TempDir::TempDir() {
  char tmpl[] = "/tmp/fastage-test.XXXXXX";
  path_ = mkdtemp(tmpl);
}

TempDir::~TempDir() {
  std::error_code ec;
  std::filesystem::remove_all(path_, ec);
}

std::string TempDir::Write(const std::string& name, const std::string& text) const {
  std::string p = path_ + "/" + name;
  std::ofstream(p) << text;
  return p;
}

CommandResult RunCommand(std::vector<std::string> argv, std::chrono::milliseconds timeout,
                         std::vector<std::string> env) {
  TempDir dir;
  if (argv[0].find('/') == std::string::npos) argv[0] = BinDir() + "/" + argv[0];
  SubprocessOptions options{
      .argv = argv, .env = env, .stdout_path = dir.path() + "/out", .stderr_path = dir.path() + "/err"};
  CommandResult result;
  auto process = Subprocess::Spawn(options);
  if (!process.ok()) {
    result.exit.exit_code = -1;
    result.err = std::string(process.status().message());
    return result;
  }
  auto exit = (*process)->Wait(timeout);
  if (!exit) {
    result.timed_out = true;
    exit = (*process)->Terminate(std::chrono::milliseconds(2000));
  }
  result.exit = *exit;
  result.out = ReadFile(dir.path() + "/out");
  result.err = ReadFile(dir.path() + "/err");
  return result;
}

PseudoTerminalPair::PseudoTerminalPair(const TempDir& dir) : dir_(dir.path()) {
  auto socat = Subprocess::Spawn({.argv = {"socat", "pty,raw,echo=0,link=" + board(), "pty,raw,echo=0,link=" + host()},
                                  .stderr_path = dir_ + "/socat.log"});
  if (!socat.ok()) {
    error_ = std::string(socat.status().message());
    return;
  }
  socat_ = std::move(*socat);
  struct stat st {};
  for (int i = 0; i < 200; ++i) {
    if (stat(board().c_str(), &st) == 0 && stat(host().c_str(), &st) == 0) {
      ok_ = true;
      return;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  error_ = "socat made no pseudo-terminal pair in 2 s: " + ReadFile(dir_ + "/socat.log");
}

PseudoTerminalPair::~PseudoTerminalPair() {
  if (socat_) socat_->Terminate(std::chrono::seconds(1));
}

}  // namespace stage::testing
