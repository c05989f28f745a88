// The stage's light as photometric stereo models it (docs/processing.md#model): every LED unit a point source in its
// direction from the stage origin at the dome's radius, with its intensity calibration; every pattern of the cycle a
// weight per unit exactly as the light nodes drive it (16-bit levels). Under pattern p a Lambertian surface point with
// normal n and albedo a near the origin returns a * n . H_p(n), where H_p(n) = sum over the units lit on n's side of
// weight_p * intensity * direction (the diffuse vector); `DiffuseTable` tabulates it over all normals.
#pragma once

#include <Eigen/Core>
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

struct LightModel {
  std::vector<Eigen::Vector3d> directions;  // unit vectors, stage frame
  std::vector<double> intensity;            // relative (the units' intensity_scale)
  double radius_mm = 1000;
  std::vector<LightPattern> patterns;  // in cycle order

  // The rig's units and pattern set (its `pattern_set`), at `sim.dome_radius_mm` (1000 by default).
  static absl::StatusOr<LightModel> FromRig(const LoadedRig& rig);
  // The index of the pattern called `name` in the cycle; NotFound names the pattern set's patterns.
  absl::StatusOr<int> Find(absl::string_view name) const;
  // H_p(n) (see above).
  Eigen::Vector3d DiffuseVector(int pattern, const Eigen::Vector3d& n) const;
  // The same at a surface point `x` (stage frame, mm) with the units at their real distance: each unit's direction
  // from x, and its light falling off with the square of its distance (relative to the dome's radius).
  Eigen::Vector3d DiffuseVectorAt(int pattern, const Eigen::Vector3d& n, const Eigen::Vector3d& x) const;
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
