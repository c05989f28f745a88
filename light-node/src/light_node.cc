// Light node logic.
#include "light_node.h"

#include "absl/strings/str_cat.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"

namespace stage::light {

absl::StatusOr<std::unique_ptr<LightNode>> LightNode::Create(const v1::LightNodeConfig& config,
                                                             std::unique_ptr<LightDriver> driver,
                                                             std::string rig_hash) {
  if (driver->Describe().channel_count != config.channel_count()) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", config.id(), "\": driver has ",
                                                      driver->Describe().channel_count,
                                                      " channels, rig says channel_count ", config.channel_count()));
  }
  return std::unique_ptr<LightNode>(new LightNode(config, std::move(driver), std::move(rig_hash)));
}

LightNode::LightNode(v1::LightNodeConfig config, std::unique_ptr<LightDriver> driver, std::string rig_hash)
    : config_(std::move(config)), driver_(std::move(driver)), rig_hash_(std::move(rig_hash)) {}

LightNode::~LightNode() {
  if (absl::Status s = driver_->Blackout(); !s.ok()) {
    Logger("light.node")->error("{}: blackout on shutdown failed: {}", config_.id(), s.message());
  }
}

v1::NodeInfo LightNode::Info() const {
  return MakeNodeInfo(config_.id(), v1::NODE_KIND_LIGHT, "", driver_->Describe().backend, rig_hash_);
}

v1::LightStats LightNode::Stats() const {
  DriverState state = driver_->State();
  v1::LightStats stats;
  switch (state.mode) {
    case DriverMode::kIdle:
      stats.set_mode(v1::LIGHT_MODE_IDLE);
      break;
    case DriverMode::kArmed:
      stats.set_mode(v1::LIGHT_MODE_ARMED);
      break;
    case DriverMode::kBlackout:
      stats.set_mode(v1::LIGHT_MODE_BLACKOUT);
      break;
  }
  stats.set_steps(state.steps);
  stats.set_current_row(state.current_row < 0 ? 0 : static_cast<uint32_t>(state.current_row));
  for (const std::string& f : state.faults) stats.add_faults(f);
  return stats;
}

}  // namespace stage::light
