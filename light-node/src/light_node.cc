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

absl::Status LightNode::Arm(const std::string& take_id, const v1::PatternTable& table) {
  PatternTable t;
  t.pattern_set = table.pattern_set();
  for (int r = 0; r < table.rows_size(); ++r) {
    const v1::PatternRow& row = table.rows(r);
    t.row_names.push_back(row.name());
    ChannelLevels levels;
    for (int c = 0; c < row.levels_size(); ++c) {
      if (row.levels(c) > 65535) {
        return absl::InvalidArgumentError(absl::StrCat("light node \"", config_.id(), "\": row ", r, " (", row.name(),
                                                       ") channel ", c, ": level ", row.levels(c), " is above 65535"));
      }
      levels.push_back(static_cast<uint16_t>(row.levels(c)));
    }
    t.rows.push_back(std::move(levels));
  }
  if (driver_->State().mode == DriverMode::kArmed) {
    if (absl::Status s = driver_->Disarm(); !s.ok()) return s;
  }
  if (absl::Status s = driver_->LoadPatternTable(t); !s.ok()) return s;
  if (absl::Status s = driver_->Arm(); !s.ok()) return s;
  Logger("light.node")->info("{}: armed for take {} ({} rows)", config_.id(), take_id, t.rows.size());
  return absl::OkStatus();
}

absl::Status LightNode::Disarm(const std::string& take_id) {
  if (driver_->State().mode != DriverMode::kArmed) return absl::OkStatus();
  Logger("light.node")->info("{}: disarmed after take {}", config_.id(), take_id);
  return driver_->Disarm();
}

}  // namespace stage::light
