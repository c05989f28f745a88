// The schedule compiler: rig + pattern set -> the exact per-slot plan of every light node and camera
// (stage.v1.Schedule). Slot k shows pattern k mod N in frame k div N; each light node switches at a fixed offset
// from the slot edge; each camera fires in the slots its divider and phase select, with its trigger, exposure and
// readout at fixed offsets. All times are integer ticks of the schedule's TimeBase (docs/timing.md).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/time_base.h"
#include "stage/v1/rig.pb.h"
#include "stage/v1/timing.pb.h"

namespace stage::timing {

// Compiles the rig's timing. The rig must have had its defaults applied and passed ValidateRig; `patterns` must
// have been resolved against the same rig's units. Fails only on what validation cannot see (an empty pattern set).
absl::StatusOr<v1::Schedule> CompileSchedule(const v1::RigConfig& rig, const PatternSet& patterns);

// FNV-1a 64 of the schedule's deterministic serialization with `hash` and `rig_hash` cleared, 16 hex digits.
std::string ScheduleHash(const v1::Schedule& schedule);

// Bytes per pixel on the wire of a pixel format (Bayer/mono 8 bit: 1; 12/16 bit unpacked: 2; RGB8: 3).
double BytesPerPixel(v1::PixelFormat format);

// True when `camera` is triggered in slot `slot`.
inline bool FiresInSlot(const v1::CameraTiming& camera, int64_t slot) {
  int64_t d = camera.divider() == 0 ? 1 : camera.divider();
  int64_t m = slot % d;
  if (m < 0) m += d;
  return m == camera.slot_phase();
}

// The first slot >= `from` in which `camera` fires.
int64_t NextFiringSlot(const v1::CameraTiming& camera, int64_t from);

// How many of slots [0, slots) `camera` fires in: the frames a take of that length expects of it.
int64_t FiringsInTake(const v1::CameraTiming& camera, int64_t slots);

// Slot `slot` spelled out: pattern, frame, the cameras that fire.
v1::SlotEntry DescribeSlot(const v1::Schedule& schedule, int64_t slot);

// Patterns per cycle (at least 1).
inline int64_t CycleLength(const v1::Schedule& schedule) {
  return schedule.patterns_size() > 0 ? schedule.patterns_size() : 1;
}

// Light node or camera by id; nullptr if absent.
const v1::CameraTiming* FindCameraTiming(const v1::Schedule& schedule, const std::string& id);
const v1::LightNodeTiming* FindLightTiming(const v1::Schedule& schedule, const std::string& id);

}  // namespace stage::timing
