// Helpers for cross-process suites: where the built programs are, running a program with a timeout and capturing
// its output, temporary directories.
#pragma once

#include <chrono>
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

}  // namespace stage::testing
