// Light backends: see backends.h.
#include "light_backends.h"


#include "absl/strings/str_cat.h"
#include "gpiod_light_driver.h"
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

void RegisterHardwareLightBackends(LightBackends* backends) {
  backends->Register(
      v1::LIGHT_BACKEND_GPIOD,
      [](const v1::LightNodeConfig& config, const LightBackendContext& context) -> absl::StatusOr<LightBackendParts> {
        auto options = GpiodDriverOptionsFromRig(config, context.slot_rate_hz);
        if (!options.ok()) return options.status();
        auto driver = GpiodLightDriver::Open(*std::move(options));
        if (!driver.ok()) return driver.status();
        LightBackendParts parts;
        parts.driver = std::move(*driver);
        return parts;
      });
#ifdef STAGE_WITH_MODBUS
  backends->Register(
      v1::LIGHT_BACKEND_MODBUS,
      [](const v1::LightNodeConfig& config, const LightBackendContext&) -> absl::StatusOr<LightBackendParts> {
        auto options = ModbusDriverOptionsFromRig(config);
        if (!options.ok()) return options.status();
        auto driver = ModbusLightDriver::Open(*std::move(options));
        if (!driver.ok()) return driver.status();
        LightBackendParts parts;
        parts.driver = std::move(*driver);
        return parts;
      });
#endif
}

}  // namespace stage::light
