// Light backends by name, chosen from the rig (or --backend). Registered explicitly.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/light/light_driver.h"
#include "stage/v1/rig.pb.h"

namespace stage::light {

// Parses "sim", "gpiod", "modbus". InvalidArgument lists the valid names.
absl::StatusOr<v1::LightBackend> ParseLightBackend(const std::string& name);
std::string LightBackendName(v1::LightBackend backend);

// A driver for `config` with `backend`, at the rig's slot rate (a gpiod node generating the slot clock runs it at
// this rate). Errors name the node and the backends this build has.
absl::StatusOr<std::unique_ptr<LightDriver>> CreateLightDriver(v1::LightBackend backend,
                                                               const v1::LightNodeConfig& config,
                                                               double slot_rate_hz);

}  // namespace stage::light
