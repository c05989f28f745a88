// Plugin modules: code a program opens (dlopen) only when it needs it, so that a library heavy to load (libtorch,
// OpenCV's image codecs with GDAL behind them) costs nothing to the processes that never use it. A module is built
// beside the programs (build/lib, next to build/bin and build/tests) and exports one extern "C" entry point.
#pragma once

#include <string>

#include "absl/status/statusor.h"

namespace stage {

struct ModuleSpec {
  std::string file;    // "libstage_torch_nets.so"
  std::string env;     // a variable naming the file elsewhere, e.g. "FASTAGE_TORCH_NETS"
  std::string entry;   // the extern "C" symbol
  std::string what;    // for errors: "the torch nets' module"
  std::string target;  // the CMake target that builds it
};

// The path `spec` resolves to: $<env> where set, else lib/<file> beside the running program's directory.
std::string ModulePath(const ModuleSpec& spec);

// Opens the module (RTLD_NOW | RTLD_LOCAL; never closed) and returns its entry point's address. FailedPrecondition
// naming the file and why (missing, dlopen's words, no entry point). Each call opens again: callers keep the result.
absl::StatusOr<void*> OpenModule(const ModuleSpec& spec);

}  // namespace stage
