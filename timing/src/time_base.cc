// TimeBase: integer ticks of 1/lcm(slot rate, 10^9) s.
#include "stage/timing/time_base.h"

#include <cmath>
#include <numeric>

#include "absl/strings/str_cat.h"

namespace stage::timing {
namespace {

constexpr int64_t kNsPerSecond = 1'000'000'000;
// 128-bit intermediates (a GCC/Clang extension; __extension__ keeps -Wpedantic quiet).
__extension__ typedef __int128 Int128;

// Rounding to the nearest for either sign (C++ division truncates towards zero).
int64_t RoundDiv(Int128 a, Int128 b) {
  // floor((2a + b) / 2b): nearest, halves up.
  Int128 num = 2 * a + b;
  Int128 den = 2 * b;
  Int128 q = num / den;
  if ((num % den != 0) && ((num < 0) != (den < 0))) --q;
  return static_cast<int64_t>(q);
}

}  // namespace

absl::StatusOr<TimeBase> TimeBase::Create(uint32_t slot_rate_hz) {
  if (slot_rate_hz < 1 || slot_rate_hz > 1'000'000) {
    return absl::InvalidArgumentError(absl::StrCat("slot rate ", slot_rate_hz, " Hz is not in [1, 1000000]"));
  }
  TimeBase base;
  base.slot_rate_hz_ = slot_rate_hz;
  base.ticks_per_second_ = std::lcm<int64_t>(slot_rate_hz, kNsPerSecond);
  base.ticks_per_slot_ = base.ticks_per_second_ / slot_rate_hz;
  base.ticks_per_ns_ = base.ticks_per_second_ / kNsPerSecond;
  return base;
}

TimeBase TimeBase::FromProto(const v1::TimeBase& proto) {
  TimeBase base;
  base.slot_rate_hz_ = proto.slot_rate_hz();
  base.ticks_per_second_ = proto.ticks_per_second();
  base.ticks_per_slot_ = proto.ticks_per_slot();
  base.ticks_per_ns_ = proto.ticks_per_ns();
  return base;
}

v1::TimeBase TimeBase::ToProto() const {
  v1::TimeBase proto;
  proto.set_slot_rate_hz(slot_rate_hz_);
  proto.set_ticks_per_second(ticks_per_second_);
  proto.set_ticks_per_slot(ticks_per_slot_);
  proto.set_ticks_per_ns(ticks_per_ns_);
  return proto;
}

int64_t TimeBase::SlotAtNs(int64_t t_ns) const {
  // t_ns * slot_rate / 10^9 without the intermediate product overflowing.
  const Int128 num = static_cast<Int128>(t_ns) * slot_rate_hz_;
  const Int128 den = 1'000'000'000;
  Int128 q = num / den;
  if ((num % den != 0) && (num < 0)) --q;
  return static_cast<int64_t>(q);
}

int64_t TimeBase::SlotStartNs(int64_t slot) const {
  return RoundDiv(static_cast<Int128>(slot) * 1'000'000'000, static_cast<Int128>(slot_rate_hz_));
}

int64_t TimeBase::TicksToNs(int64_t ticks) const { return RoundDiv(ticks, ticks_per_ns_); }

int64_t TimeBase::UsToTicks(double us) const { return std::llround(us * 1000.0) * ticks_per_ns_; }

int64_t TimeBase::TicksToUnits(int64_t ticks, int64_t unit_fs) const {
  // ticks * 10^15 / ticks_per_second fs, divided by unit_fs; 128-bit so that a day of ticks times 10^15 fits.
  return RoundDiv(static_cast<Int128>(ticks) * 1'000'000'000'000'000, static_cast<Int128>(ticks_per_second_) * unit_fs);
}

}  // namespace stage::timing
