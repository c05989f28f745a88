// OpenGpiodLines in a build without libgpiod (STAGE_WITH_GPIOD=OFF): the gpiod backend says so by name.
#include "absl/strings/str_cat.h"
#include "gpio_lines.h"

namespace stage::light {

absl::StatusOr<std::unique_ptr<GpioLines>> OpenGpiodLines(const GpiodLinesOptions& options) {
  return absl::UnimplementedError(
      absl::StrCat("GPIO chip \"", options.chip, "\": this build has no gpiod backend (STAGE_WITH_GPIOD=OFF)"));
}

}  // namespace stage::light
