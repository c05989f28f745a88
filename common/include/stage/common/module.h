// Plugin modules: code a program opens (dlopen) only when it needs it, so that a library heavy to load (libtorch,
// OpenCV's image codecs with GDAL behind them) costs nothing to the processes that never use it. A module is built
// beside the programs (build/lib, next to build/bin and build/tests) and exports one extern "C" entry point.
#pragma once

#include <string>

#include "absl/status/statusor.h"

namespace stage {

struct ModuleSpec {
  // The CMake target that builds it (stage_module), "stage_torch_nets": the file is lib<target>.so, and
  // $FASTAGE_<target without "stage_", in capitals> (FASTAGE_TORCH_NETS) may name another.
  std::string target;
  std::string entry;  // the extern "C" symbol
  std::string what;   // for errors: "the torch nets' module"
};

// The variable that may name the module's file: "FASTAGE_TORCH_NETS" for target "stage_torch_nets".
std::string ModuleVariable(const ModuleSpec& spec);
// The path `spec` resolves to: the file the variable names where set, else lib/lib<target>.so beside the running
// program's directory.
std::string ModulePath(const ModuleSpec& spec);

// Opens the module (RTLD_NOW | RTLD_LOCAL; never closed) and returns its entry point's address. FailedPrecondition
// naming the file and why (missing, dlopen's words, no entry point). Each call opens again: callers keep the result.
absl::StatusOr<void*> OpenModule(const ModuleSpec& spec);

// OpenModule for a module whose entry point takes nothing and returns a `T` (a function of the module): the entry
// called.
template <typename T>
absl::StatusOr<T> OpenModuleAs(const ModuleSpec& spec) {
  absl::StatusOr<void*> entry = OpenModule(spec);
  if (!entry.ok()) return entry.status();
  return reinterpret_cast<T (*)()>(*entry)();
}

}  // namespace stage
