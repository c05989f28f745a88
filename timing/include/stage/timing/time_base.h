// Exact slot time. Every schedule time is an integer number of ticks of 1/lcm(slot_rate_hz, 10^9) s, so that a slot
// and a nanosecond are both whole numbers of ticks: slot k starts at exactly k / slot_rate_hz s whatever k is, and
// nothing accumulates rounding over a take (rounding the 912 Hz period to whole ns would drift 0.75 ms per hour).
#pragma once

#include <climits>
#include <cstdint>

#include "absl/status/statusor.h"
#include "stage/v1/timing.pb.h"

namespace stage::timing {

class TimeBase {
 public:
  // InvalidArgument unless 1 <= slot_rate_hz <= 1'000'000.
  static absl::StatusOr<TimeBase> Create(uint32_t slot_rate_hz);
  static TimeBase FromProto(const v1::TimeBase& proto);
  v1::TimeBase ToProto() const;

  uint32_t slot_rate_hz() const { return slot_rate_hz_; }
  int64_t ticks_per_second() const { return ticks_per_second_; }
  int64_t ticks_per_slot() const { return ticks_per_slot_; }
  int64_t ticks_per_ns() const { return ticks_per_ns_; }

  // Start of slot `slot` (which may be negative), ticks since slot 0. Exact for |slot| <= max_slot() (at 912 Hz
  // about 1.5e11 slots, five years); schedules, windows and takes are kept within that range.
  int64_t SlotStartTicks(int64_t slot) const { return slot * ticks_per_slot_; }
  int64_t max_slot() const { return INT64_MAX / ticks_per_slot_; }
  // Slot `slot`'s start rounded to the nearest nanosecond (halves up), computed from the exact time for any slot
  // whose time fits in int64 ns (292 years). Each value is rounded on its own, so the error is at most 0.5 ns for
  // every slot of any take: there is no drift.
  int64_t SlotStartNs(int64_t slot) const;
  // The slot that contains `t_ns` (ns since slot 0): floor division of the exact times, for any int64 `t_ns`.
  int64_t SlotAtNs(int64_t t_ns) const;

  // Nearest nanosecond (halves up), for ticks of either sign.
  int64_t TicksToNs(int64_t ticks) const;
  int64_t NsToTicks(int64_t ns) const { return ns * ticks_per_ns_; }
  // Microseconds from a configuration file, resolved to the nearest nanosecond, in ticks.
  int64_t UsToTicks(double us) const;
  // For display only: ticks as (fractional) microseconds.
  double TicksToUs(int64_t ticks) const { return static_cast<double>(ticks) * 1e6 / ticks_per_second_; }

  // Ticks rounded to the nearest multiple of `unit_fs` femtoseconds, in those units (the VCD writer's timescale).
  int64_t TicksToUnits(int64_t ticks, int64_t unit_fs) const;

 private:
  uint32_t slot_rate_hz_ = 0;
  int64_t ticks_per_second_ = 0;
  int64_t ticks_per_slot_ = 0;
  int64_t ticks_per_ns_ = 0;
};

}  // namespace stage::timing
