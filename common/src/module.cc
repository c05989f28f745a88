// Plugin modules: see module.h.
#include "stage/common/module.h"

#include <dlfcn.h>

#include <cstdlib>
#include <filesystem>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "stage/common/logging.h"

namespace stage {

std::string ModuleVariable(const ModuleSpec& spec) {
  return absl::AsciiStrToUpper(absl::StrCat("FASTAGE_", absl::StripPrefix(spec.target, "stage_")));
}

std::string ModulePath(const ModuleSpec& spec) {
  const std::string variable = ModuleVariable(spec);
  if (const char* path = std::getenv(variable.c_str()); path != nullptr && *path != '\0') return path;
  const std::string file = absl::StrCat("lib", spec.target, ".so");
  std::error_code ec;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (ec) return file;
  return (self.parent_path().parent_path() / "lib" / file).string();
}

absl::StatusOr<void*> OpenModule(const ModuleSpec& spec) {
  const std::string path = ModulePath(spec);
  auto failed = [&](const std::string& why) {
    return absl::FailedPreconditionError(absl::StrCat(spec.what, " ", path, ": ", why,
                                                      " (built with the programs as target ", spec.target, "; $",
                                                      ModuleVariable(spec), " names another)"));
  };
  std::error_code ec;
  // A bare name is dlopen's to find on the library path.
  if (path.find('/') != std::string::npos && !std::filesystem::exists(path, ec)) return failed("no such file");
  void* module = dlopen(path.c_str(), RTLD_NOW | RTLD_LOCAL);
  if (module == nullptr) return failed(dlerror());
  void* entry = dlsym(module, spec.entry.c_str());
  if (entry == nullptr) return failed(absl::StrCat("no entry point ", spec.entry));
  Logger("common")->debug("opened {}", path);
  return entry;
}

}  // namespace stage
