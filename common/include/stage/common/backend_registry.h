// The backends a node program has, registered in main() and chosen by the rig's `backend` enum (or --backend): one
// registry shape for camera and light nodes, so that both are chosen the same way and a missing one reads the same
// ("camera \"mv-01\": this program has no aravis backend (it has: sim)").
#pragma once

#include <functional>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace stage {

// Key: the rig's backend enum; Config: the node's rig entry (with id()); Context: what a backend needs beyond it;
// Parts: what a backend makes.
template <typename Key, typename Config, typename Context, typename Parts>
class BackendRegistry {
 public:
  using Factory = std::function<absl::StatusOr<Parts>(const Config&, const Context&)>;

  // `kind` names a node in messages ("camera", "light node"); `name` gives a backend's short name ("aravis").
  BackendRegistry(std::string kind, std::string (*name)(Key)) : kind_(std::move(kind)), name_(name) {}

  void Register(Key backend, Factory factory) { factories_[backend] = std::move(factory); }

  // The node's device from `backend`. InvalidArgument names the node and the backends this program has for one it
  // lacks; the backend's own errors name the node and its device.
  absl::StatusOr<Parts> Create(Key backend, const Config& config, const Context& context) const {
    auto it = factories_.find(backend);
    if (it == factories_.end()) {
      return absl::InvalidArgumentError(absl::StrCat(kind_, " \"", config.id(), "\": this program has no ",
                                                     name_(backend), " backend (it has: ", Names(), ")"));
    }
    return it->second(config, context);
  }

  // "sim, aravis": the registered backends, in the enum's order.
  std::string Names() const {
    std::vector<std::string> names;
    for (const auto& [backend, factory] : factories_) names.push_back(name_(backend));
    return names.empty() ? "none" : absl::StrJoin(names, ", ");
  }

 private:
  std::string kind_;
  std::string (*name_)(Key);
  std::map<Key, Factory> factories_;
};

}  // namespace stage
