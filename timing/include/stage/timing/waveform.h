// Waveforms of a schedule: the planned signals of a window of slots, as VCD (IEEE 1364 value change dump, for
// GTKWave and sigrok/PulseView) and as an SVG timing diagram for people (docs/timing.md shows both).
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/v1/timing.pb.h"

namespace stage::timing {

// Slots [first_slot, first_slot + slot_count).
struct WaveformWindow {
  int64_t first_slot = 0;
  int64_t slot_count = 38;
};

// One planned digital signal: where it is high, as half-open tick intervals [start, end) since slot 0, merged and
// clipped to the window.
struct Signal {
  // Unique, flat name (readers such as sigrok ignore VCD scopes): "slot_clock", "pattern_id[3]", "hs-1_exposure".
  std::string name;
  // VCD scope path ("cameras/hs-1"), for viewers that show a tree.
  std::string scope;
  // What it shows, for the VCD comment and the SVG legend.
  std::string description;
  std::vector<std::pair<int64_t, int64_t>> high;
};

// Every signal of the window, in a fixed order: slot_clock, cycle_start, divided clocks of the cameras
// (clock_div<d>_phase<p>), pattern_id bits (MSB first; [0] is the LSB), steady_window, per light node <id>_step, per
// camera <id>_trigger, <id>_exposure, <id>_readout.
std::vector<Signal> PlannedSignals(const v1::Schedule& schedule, const WaveformWindow& window);

// The name a signal gets in the VCD: a Verilog identifier (IEEE 1364 references are identifiers), so '-', '.' and
// anything else outside [A-Za-z0-9_$] becomes '_': "mv-01_exposure" -> "mv_01_exposure". Bit selects stay
// ("pattern_id[3]"). sigrok-cli also needs this: its channel lists read '-' as a range.
std::string VcdName(absl::string_view name);

struct VcdOptions {
  // VCD timescale in femtoseconds: 1, 10 or 100 times a power of 1000 (1 fs .. 100 s). Default 1 ns. Each edge is the
  // exact schedule time rounded on its own to the nearest unit, so edges are exact to half a unit and never drift.
  int64_t timescale_fs = 1'000'000;
};

// "1 ns", "10 ps", ... for a valid timescale; InvalidArgument otherwise.
absl::StatusOr<std::string> TimescaleName(int64_t timescale_fs);
// Parses "1ns", "1 ns", "100ps"; InvalidArgument naming the value and the valid forms.
absl::StatusOr<int64_t> ParseTimescale(const std::string& text);

// The window as VCD text. InvalidArgument for an empty window or an invalid timescale.
absl::StatusOr<std::string> ScheduleToVcd(const v1::Schedule& schedule, const WaveformWindow& window,
                                          const VcdOptions& options = {});

// The window as an SVG timing diagram: slots labelled with pattern names, the steady-light window shaded, each light
// node's switching, each camera's trigger, exposure and readout; violations from `report` marked in red (exposure
// outside the steady light drawn where it happens, every other violation listed under the diagram).
absl::StatusOr<std::string> ReportToSvg(const v1::TimingReport& report, const WaveformWindow& window);

}  // namespace stage::timing
