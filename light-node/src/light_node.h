// The light node's logic: owns the driver, answers for the service. Dark on every path out.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/light/light_driver.h"
#include "stage/v1/light_node.pb.h"
#include "stage/v1/node.pb.h"
#include "stage/v1/rig.pb.h"

namespace stage::light {

class LightNode {
 public:
  static absl::StatusOr<std::unique_ptr<LightNode>> Create(const v1::LightNodeConfig& config,
                                                           std::unique_ptr<LightDriver> driver, std::string rig_hash);
  // Blacks out the driver: lights fail dark.
  ~LightNode();

  v1::NodeInfo Info() const;
  v1::LightStats Stats() const;
  // Loads `table` and arms (disarming first if armed); see LightNode.Arm in light_node.proto.
  absl::Status Arm(const std::string& take_id, const v1::PatternTable& table);
  absl::Status Disarm(const std::string& take_id);

 private:
  LightNode(v1::LightNodeConfig config, std::unique_ptr<LightDriver> driver, std::string rig_hash);
  v1::LightNodeConfig config_;
  std::unique_ptr<LightDriver> driver_;
  std::string rig_hash_;
};

}  // namespace stage::light
