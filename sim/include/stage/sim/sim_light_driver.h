// A simulated LED controller behind the LightDriver interface: holds the pattern table, steps on slot edges given
// by the simulator (Step()), and reports its channel outputs. Safety behaviour (blackout latch) as on hardware.
#pragma once

#include <mutex>
#include <string>

#include "stage/light/light_driver.h"

namespace stage::sim {

class SimLightDriver final : public light::LightDriver {
 public:
  SimLightDriver(std::string node_id, uint32_t channel_count);

  light::DriverDescription Describe() const override;
  absl::Status LoadPatternTable(const light::PatternTable& table) override;
  absl::Status Arm() override;
  absl::Status Disarm() override;
  absl::Status Blackout() override;
  absl::Status ResetBlackout() override;
  light::DriverState State() const override;

  // A slot-clock edge: when armed, applies the next row of the table.
  void Step();
  // The levels on the channels now (all zero when dark).
  light::ChannelLevels Outputs() const;

 private:
  std::string node_id_;
  uint32_t channel_count_;
  mutable std::mutex mutex_;
  light::PatternTable table_;  // guarded by mutex_
  bool table_loaded_ = false;  // guarded by mutex_
  light::DriverState state_;   // guarded by mutex_
};

}  // namespace stage::sim
