// A light driver's record of a take's faults (DriverState::take_faults), shared by the hardware backends.
#pragma once

#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"

namespace stage::light {

// Adds "<stamp> <kind><detail>" to `take_faults`, stamped with when it was first seen ("10:41:07.512 board not
// answering: status poll ..."), once per take and kind: a kind already recorded is not added again, whatever its
// detail now (a temperature, an error text), so one fault that lasts is one entry, with what was seen first.
inline void RecordTakeFault(std::vector<std::string>* take_faults, const std::string& kind,
                            const std::string& detail = "") {
  for (const std::string& f : *take_faults) {
    const size_t text = f.find(' ') + 1;  // after the stamp
    if (f.compare(text, kind.size(), kind) == 0) return;
  }
  take_faults->push_back(
      absl::StrCat(absl::FormatTime("%H:%M:%E3S", absl::Now(), absl::LocalTimeZone()), " ", kind, detail));
}

}  // namespace stage::light
