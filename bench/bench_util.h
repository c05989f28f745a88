// What the light benchmarks share: timing in ms, medians, dying with a message, and the shipped rig with its
// compiled schedule.
#pragma once

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "stage/common/rig.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/schedule.h"
#include "stage/v1/timing.pb.h"

namespace stage::bench {

using Clock = std::chrono::steady_clock;
inline double Ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

inline double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

[[noreturn]] inline void Die(const char* program, const std::string& what) {
  std::fprintf(stderr, "%s: %s\n", program, what.c_str());
  std::exit(1);
}

struct ShippedRig {
  LoadedRig rig;
  v1::Schedule schedule;
};

// The built-in rig and its schedule compiled; dies naming `program` when either fails.
inline ShippedRig LoadShippedRig(const char* program) {
  auto rig = LoadRig(kBuiltinRigName);
  if (!rig.ok()) Die(program, std::string(rig.status().message()));
  auto patterns = timing::LoadRigPatternSet(rig->rig, rig->base_dir);
  if (!patterns.ok()) Die(program, std::string(patterns.status().message()));
  auto schedule = timing::CompileSchedule(rig->rig, *patterns);
  if (!schedule.ok()) Die(program, std::string(schedule.status().message()));
  return {*std::move(rig), *std::move(schedule)};
}

}  // namespace stage::bench
