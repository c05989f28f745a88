// Simulated LED controller.
#include "stage/sim/sim_light_driver.h"

#include "absl/strings/str_cat.h"

namespace stage::sim {

SimLightDriver::SimLightDriver(std::string node_id, uint32_t channel_count)
    : node_id_(std::move(node_id)), channel_count_(channel_count) {
  state_.channel_count = channel_count;
}

light::DriverDescription SimLightDriver::Describe() const { return {"sim", "sim:" + node_id_, channel_count_}; }

absl::Status SimLightDriver::LoadPatternTable(const light::PatternTable& table) {
  if (table.rows.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", node_id_, "\": pattern table has no rows"));
  }
  for (size_t r = 0; r < table.rows.size(); ++r) {
    if (table.rows[r].size() != channel_count_) {
      return absl::InvalidArgumentError(absl::StrCat("light node \"", node_id_, "\": pattern table row ", r, " has ",
                                                     table.rows[r].size(), " levels, the node has ", channel_count_,
                                                     " channels"));
    }
  }
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": load a table only when idle"));
  }
  table_ = table;
  table_loaded_ = true;
  return absl::OkStatus();
}

absl::Status SimLightDriver::Arm() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": arm only when idle"));
  }
  if (!table_loaded_) {
    return absl::FailedPreconditionError(absl::StrCat("light node \"", node_id_, "\": no pattern table loaded"));
  }
  state_.mode = light::DriverMode::kArmed;
  state_.current_row = -1;
  state_.steps = 0;
  return absl::OkStatus();
}

absl::Status SimLightDriver::Disarm() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode == light::DriverMode::kArmed) state_.mode = light::DriverMode::kIdle;
  state_.current_row = -1;
  return absl::OkStatus();
}

absl::Status SimLightDriver::Blackout() {
  std::lock_guard<std::mutex> lock(mutex_);
  state_.mode = light::DriverMode::kBlackout;
  state_.current_row = -1;
  return absl::OkStatus();
}

absl::Status SimLightDriver::ResetBlackout() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode == light::DriverMode::kBlackout) state_.mode = light::DriverMode::kIdle;
  return absl::OkStatus();
}

light::DriverState SimLightDriver::State() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return state_;
}

void SimLightDriver::Step() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kArmed) return;
  state_.current_row = static_cast<int>(state_.steps % table_.rows.size());
  ++state_.steps;
}

light::ChannelLevels SimLightDriver::Outputs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (state_.mode != light::DriverMode::kArmed || state_.current_row < 0) {
    return light::ChannelLevels(channel_count_, 0);
  }
  return table_.rows[static_cast<size_t>(state_.current_row)];
}

}  // namespace stage::sim
