// A performance written as the YAML file Performance::FromYaml reads (`keys: [{t, <expression weights>, yaw, pitch,
// roll, x, y, z, sequence}, ...]`), so that a drawn performance (a range of motion of any length) can be edited, kept
// with a take, or named by a rig's sim.subject.performance.
#pragma once

#include <string>

#include "absl/status/status.h"
#include "stage/sim/head.h"

namespace stage::sim {

// Writes `performance` to `path`: every key with its time, every expression weight, the rotation and the
// translation, and the sequence that starts at it. Read back by Performance::FromYaml it gives the same poses to the
// bit (floats written with 9 significant digits, times with 17). A sequence that starts between keys cannot be
// written (FromYaml starts a sequence at a key): InvalidArgument. Errors name the file.
absl::Status WritePerformanceYaml(const Performance& performance, const std::string& path);

}  // namespace stage::sim
