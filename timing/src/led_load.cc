// LED channel load: duty cycle and first-order thermal peak.
#include "stage/timing/led_load.h"

#include <algorithm>
#include <cmath>

namespace stage::timing {

LedLoad ComputeLedLoad(std::span<const double> drive, double slot_s, double tau_s, int64_t take_slots) {
  LedLoad load;
  const auto rows = static_cast<int64_t>(drive.size());
  if (rows == 0) return load;
  double sum = 0;
  for (double u : drive) sum += u;
  load.duty = sum / static_cast<double>(rows);
  // Load L relaxes towards the drive u with time constant tau; over a slot of constant drive, L' = u + (L - u) a with
  // a = exp(-slot / tau). It is monotonic within a slot, so its peak is at a slot edge. From cold, each cycle maps its
  // start L to a^N L + b; the start values grow towards the fixed point b / (1 - a^N), and a later cycle's trajectory
  // lies above an earlier one's, so the peak over the take is in its last full cycle (or the partial one after it).
  const double a = std::exp(-slot_s / tau_s);
  auto run = [&](double start, int64_t slots, double* peak) {
    double l = start;
    for (int64_t k = 0; k < slots; ++k) {
      const double v = drive[static_cast<size_t>(k % rows)];
      l = v + (l - v) * a;
      *peak = std::max(*peak, l);
    }
    return l;
  };
  double ignored = 0;
  const double b = run(0.0, rows, &ignored);
  const double aN = std::pow(a, static_cast<double>(rows));
  const int64_t cycles = take_slots / rows;
  const int64_t rest = take_slots % rows;
  if (cycles == 0) {
    run(0.0, rest, &load.peak);
  } else {
    const double fixed = aN < 1 ? b / (1 - aN) : 0.0;
    const double start_last = fixed * (1 - std::pow(aN, static_cast<double>(cycles - 1)));
    const double end_last = run(start_last, rows, &load.peak);
    run(end_last, rest, &load.peak);
  }
  return load;
}

}  // namespace stage::timing
