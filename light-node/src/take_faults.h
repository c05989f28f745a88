// A light driver's record of a take's faults (DriverState::take_faults), shared by the hardware backends.
#pragma once

#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"

namespace stage::light {

// Adds `fault` to `take_faults`, stamped with when it was first seen ("10:41:07.512 board not answering: ..."), once
// per take: a fault already recorded (by its text after the stamp) is not added again.
inline void RecordTakeFault(std::vector<std::string>* take_faults, const std::string& fault) {
  for (const std::string& f : *take_faults) {
    if (f.size() >= fault.size() && f.compare(f.size() - fault.size(), fault.size(), fault) == 0) return;
  }
  take_faults->push_back(absl::StrCat(absl::FormatTime("%H:%M:%E3S", absl::Now(), absl::LocalTimeZone()), " ", fault));
}

}  // namespace stage::light
