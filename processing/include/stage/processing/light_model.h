// The stage's light as photometric stereo models it (docs/processing.md#model): every LED unit a point source at its
// place on the dome (its direction from the stage origin times the dome's radius) with its intensity calibration;
// every pattern of the cycle a weight per unit exactly as the light nodes drive it (16-bit levels).
//
// A surface point sees each unit from its own direction, with the light falling off with the square of the distance,
// and only where nothing hides it (`UnitView`). From a point near the stage origin with nothing hidden, a Lambertian
// surface with normal n and albedo a returns a * n . H_p(n) under pattern p, where H_p(n) = sum over the units lit on
// n's side of weight_p * intensity * direction (the diffuse vector); `DiffuseTable` tabulates it over all normals.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/common/rig.h"

namespace stage::processing {

struct LightPattern {
  std::string name;
  bool parallel = false;
  // One weight per unit in [0, 1], as driven: round(w * 65535) / 65535.
  std::vector<double> weights;
};

// How one surface point sees the units: for every unit, its direction from the point (unit vector, stage frame) and
// the light that arrives (intensity x (radius / distance)^2; 0 where the unit is hidden).
struct UnitView {
  std::vector<Eigen::Vector3f> direction;
  std::vector<float> gain;
};

struct LightModel {
  std::vector<Eigen::Vector3d> directions;  // unit vectors, stage frame
  std::vector<double> intensity;            // relative (the units' intensity_scale)
  double radius_mm = 1000;
  std::vector<LightPattern> patterns;  // in cycle order

  // The rig's units and pattern set (its `pattern_set`), at `sim.dome_radius_mm` (1000 by default).
  static absl::StatusOr<LightModel> FromRig(const LoadedRig& rig);
  int units() const { return static_cast<int>(directions.size()); }
  // The index of the pattern called `name` in the cycle; NotFound names the pattern set's patterns.
  absl::StatusOr<int> Find(absl::string_view name) const;
  // H_p(n) (see above), every unit from the stage origin.
  Eigen::Vector3d DiffuseVector(int pattern, const Eigen::Vector3d& n) const;
  // The units from point `x`; `visible` (null: all) has bit l % 64 of word l / 64 set for every unit l nothing hides.
  void ViewFrom(const Eigen::Vector3d& x, const uint64_t* visible, UnitView* view) const;
  // The units from the stage origin, nothing hidden.
  UnitView ViewFromOrigin() const;
};

// H_p(n) for a list of patterns, tabulated over the sphere of normals on an octahedral map (size x size cells),
// interpolated bilinearly.
class DiffuseTable {
 public:
  DiffuseTable(const LightModel& model, const std::vector<int>& patterns, int size = 128);
  int patterns() const { return static_cast<int>(patterns_.size()); }
  // Writes H_p(n) of every tabulated pattern into `out` (3 floats each, in the order given).
  void Lookup(const Eigen::Vector3f& n, float* out) const;

 private:
  std::vector<int> patterns_;
  int size_;
  std::vector<float> table_;  // [cell][pattern][3]
};

// Octahedral mapping of unit vectors to [0, 1]^2 and back.
Eigen::Vector2f OctEncode(const Eigen::Vector3f& n);
Eigen::Vector3f OctDecode(const Eigen::Vector2f& uv);

}  // namespace stage::processing
