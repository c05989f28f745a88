// The LED units of the simulated dome: where each is, how bright (its calibration) and which channels of which light
// node drive its two emitters. Units are listed light node by light node, in rig order, as the pattern sets number
// them.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "stage/v1/rig.pb.h"

namespace stage::sim {

struct LedUnitModel {
  std::string id;
  // Unit direction from the head centre (normalized) and position, stage frame, mm.
  Eigen::Vector3d direction = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
  // Radiant intensity of each emitter at full drive, relative (the unit's intensity_scale).
  double intensity = 1;
  // Index of its light node in the rig, and its channels there.
  int node = 0;
  uint32_t parallel_channel = 0;
  uint32_t cross_channel = 0;
};

struct Dome {
  std::vector<LedUnitModel> units;

  // The rig's units at `radius_mm` from the head centre.
  static Dome FromRig(const v1::RigConfig& rig, double radius_mm);
  // Units at the given directions (normalized here), all of intensity `intensity` (tests).
  static Dome FromDirections(const std::vector<Eigen::Vector3d>& directions, double radius_mm, double intensity = 1);
};

// `n` directions spread evenly over the whole sphere (a Fibonacci lattice).
std::vector<Eigen::Vector3d> FibonacciSphere(int n);

}  // namespace stage::sim
