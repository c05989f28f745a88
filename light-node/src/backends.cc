// Light backend selection.
#include "backends.h"

#include "absl/strings/str_cat.h"
#include "gpiod_light_driver.h"
#include "stage/sim/sim_light_driver.h"
#ifdef STAGE_WITH_MODBUS
#include "modbus_light_driver.h"
#endif

namespace stage::light {

absl::StatusOr<v1::LightBackend> ParseLightBackend(const std::string& name) {
  if (name == "sim") return v1::LIGHT_BACKEND_SIM;
  if (name == "gpiod") return v1::LIGHT_BACKEND_GPIOD;
  if (name == "modbus") return v1::LIGHT_BACKEND_MODBUS;
  return absl::InvalidArgumentError(absl::StrCat("unknown light backend \"", name, "\" (sim, gpiod, modbus)"));
}

std::string LightBackendName(v1::LightBackend backend) {
  switch (backend) {
    case v1::LIGHT_BACKEND_SIM:
      return "sim";
    case v1::LIGHT_BACKEND_GPIOD:
      return "gpiod";
    case v1::LIGHT_BACKEND_MODBUS:
      return "modbus";
    default:
      return "unspecified";
  }
}

absl::StatusOr<std::unique_ptr<LightDriver>> CreateLightDriver(v1::LightBackend backend,
                                                               const v1::LightNodeConfig& config,
                                                               double slot_rate_hz) {
  switch (backend) {
    case v1::LIGHT_BACKEND_SIM:
      return std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count());
    case v1::LIGHT_BACKEND_MODBUS: {
#ifdef STAGE_WITH_MODBUS
      auto options = ModbusDriverOptionsFromRig(config);
      if (!options.ok()) return options.status();
      auto driver = ModbusLightDriver::Open(*std::move(options));
      if (!driver.ok()) return driver.status();
      return std::unique_ptr<LightDriver>(std::move(*driver));
#else
      return absl::UnimplementedError(absl::StrCat("light node \"", config.id(),
                                                   "\": this build has no modbus backend (STAGE_WITH_MODBUS=OFF)"));
#endif
    }
    case v1::LIGHT_BACKEND_GPIOD: {
      auto options = GpiodDriverOptionsFromRig(config, slot_rate_hz);
      if (!options.ok()) return options.status();
      auto driver = GpiodLightDriver::Open(*std::move(options));
      if (!driver.ok()) return driver.status();
      return std::unique_ptr<LightDriver>(std::move(*driver));
    }
    default:
      return absl::InvalidArgumentError(absl::StrCat("light node \"", config.id(), "\": backend is not set"));
  }
}

}  // namespace stage::light
