// What the LEDs of the simulated stage actually did: each driver channel's drive level over time, as the light
// drivers set it, and the light it gave: a linear ramp to each new level over the emitter's rise time (going up) or
// fall time (going down). Cameras integrate it over their exposure windows, so a late node or an exposure that
// straddles a slot edge shows in the image exactly as it would on the stage.
#pragma once

#include <cstdint>
#include <map>
#include <mutex>
#include <vector>

#include "stage/sim/dome.h"
#include "stage/sim/light_transport.h"

namespace stage::sim {

// One channel's light output over time (ns on the world's clock), relative to full drive.
class ChannelWaveform {
 public:
  ChannelWaveform(int64_t rise_ns = 0, int64_t fall_ns = 0) : rise_ns_(rise_ns), fall_ns_(fall_ns) {}
  // The drive changes to `level` (0..1) at `t_ns`. Steps must come in time order; one at the time of the previous
  // replaces it.
  void Step(int64_t t_ns, double level);
  // Output at `t_ns`.
  double At(int64_t t_ns) const;
  // The integral of the output over [t0, t1], in level x ns.
  double Integral(int64_t t0_ns, int64_t t1_ns) const;
  // Drops the steps that queries starting at or after `t_ns` do not need (the output they led to is kept).
  void Forget(int64_t t_ns);
  size_t steps() const { return steps_.size(); }

 private:
  struct StepAt {
    int64_t t;
    double level;  // the new drive
    double start;  // the output when it took effect
  };
  // The output of a ramp that started at `t` from `start` towards `level`, at time x >= t.
  double Ramp(const StepAt& s, int64_t x) const;
  // When that ramp reaches its level.
  int64_t Reach(const StepAt& s) const;
  // The integral of that ramp's output over [a, b], t <= a <= b.
  double RampIntegral(const StepAt& s, int64_t a, int64_t b) const;
  int64_t rise_ns_, fall_ns_;
  std::vector<StepAt> steps_;
};

// A broken LED unit (a fault knob): dark, or emitting `delay_ns` after its driver says (a slow or badly wired unit).
struct UnitFault {
  bool dead = false;
  int64_t delay_ns = 0;
};

// Every channel of every light node, keyed by (node index, channel), and the dome that maps channels to emitters.
class EmissionState {
 public:
  // `rise_ns`/`fall_ns` per node (its slowest emitter).
  EmissionState(const Dome& dome, std::vector<int64_t> rise_ns, std::vector<int64_t> fall_ns);

  // Node `node` sets its channels to `levels` (index = channel, 0..1) at `t_ns`. Thread-safe.
  void SetLevels(int node, int64_t t_ns, const std::vector<double>& levels);
  // Node `node` goes dark (blackout, crash) at `t_ns`.
  void Dark(int node, int64_t t_ns);

  // Unit `unit` (dome index) fails as `fault` says from now on (a default UnitFault repairs it).
  void SetUnitFault(size_t unit, UnitFault fault);
  // Drops what exposures starting at or after `t_ns` do not need.
  void Forget(int64_t t_ns);

  // Each unit's emitters' average output over [t0, t1] (the exposure), for RenderRadiance.
  EmitterLevels AverageLevels(int64_t t0_ns, int64_t t1_ns) const;

 private:
  const Dome& dome_;
  std::vector<int64_t> rise_ns_, fall_ns_;
  mutable std::mutex mutex_;
  std::map<std::pair<int, uint32_t>, ChannelWaveform> channels_;  // guarded by mutex_
  std::map<size_t, UnitFault> unit_faults_;                       // guarded by mutex_
};

}  // namespace stage::sim
