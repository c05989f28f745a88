// Helpers for cross-process suites: where the built programs are, running a program with a timeout and capturing
// its output, temporary directories.
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "stage/common/subprocess.h"

namespace stage::testing {

// build/bin, from $FASTAGE_BIN_DIR (set by CTest).
std::string BinDir();

struct CommandResult {
  ExitInfo exit;
  bool timed_out = false;
  std::string out;
  std::string err;
};

// Runs `argv` (argv[0] relative to BinDir() unless it contains '/'), kills it after `timeout`.
CommandResult RunCommand(std::vector<std::string> argv, std::chrono::milliseconds timeout,
                         std::vector<std::string> env = {});

// A fresh directory under /tmp, removed with everything in it on destruction.
class TempDir {
 public:
  TempDir();
  ~TempDir();
  const std::string& path() const { return path_; }
  std::string Write(const std::string& name, const std::string& text) const;

 private:
  std::string path_;
};

std::string ReadFile(const std::string& path);

// Every file under `root`, by its path relative to it, with its bytes (to compare what two runs wrote).
std::map<std::string, std::string> FilesUnder(const std::string& root);

// A pseudo-terminal pair made by socat (a serial line for RTU tests): `board()` and `host()` are its two ends, links in
// `dir`. Check ok() (socat started and both ends appeared); socat is ended on destruction.
class PseudoTerminalPair {
 public:
  explicit PseudoTerminalPair(const TempDir& dir);
  ~PseudoTerminalPair();
  bool ok() const { return ok_; }
  const std::string& error() const { return error_; }
  std::string board() const { return dir_ + "/board"; }
  std::string host() const { return dir_ + "/host"; }

 private:
  std::string dir_;
  std::unique_ptr<Subprocess> socat_;
  bool ok_ = false;
  std::string error_;
};

}  // namespace stage::testing
