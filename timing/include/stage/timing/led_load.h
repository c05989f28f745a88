// The thermal load of one LED channel stepping through a pattern table: its duty cycle (mean drive) and the peak of a
// first-order thermal model over a take. Used by the verifier (the schedule) and by each light node before it arms
// (the table it is actually given), so both judge a table the same way.
#pragma once

#include <cstdint>
#include <span>

namespace stage::timing {

struct LedLoad {
  // Mean drive over the table's cycle, fraction of full drive.
  double duty = 0;
  // Highest load of the thermal model during the take, from cold, fraction of full drive: what max_duty_cycle bounds.
  double peak = 0;
};

// `drive`: the channel's drive in each row of the table (fraction of full drive, 0..1), row r in slots k with
// k mod rows == r; `slot_s`: slot period; `tau_s`: thermal time constant; `take_slots`: slots the take runs.
LedLoad ComputeLedLoad(std::span<const double> drive, double slot_s, double tau_s, int64_t take_slots);

}  // namespace stage::timing
