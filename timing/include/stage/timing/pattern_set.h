// Pattern sets: named lists of illumination patterns, each a weight in [0, 1] per LED unit (docs/patterns.md).
// Files are YAML (stage.v1.PatternSetFile); the shipped default `fastage-38` is compiled in.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/v1/rig.pb.h"
#include "stage/v1/timing.pb.h"

namespace stage::timing {

inline constexpr absl::string_view kFastage38 = "fastage-38";

// A LED unit as the pattern set sees it: its id and its (normalized) direction.
struct UnitRef {
  std::string id;
  double x = 0, y = 0, z = 0;
};

// Every LED unit of the rig, light node by light node, in file order; directions normalized to unit length.
std::vector<UnitRef> RigUnits(const v1::RigConfig& rig);

struct Pattern {
  std::string name;
  v1::Polarization polarization = v1::POLARIZATION_UNSPECIFIED;
  // One weight per unit, in the order of the units the set was resolved against; each in [0, 1].
  std::vector<double> weights;
};

struct PatternSet {
  std::string name;
  std::string description;
  // Where it came from ("fastage-38 (built in)" or the file path), for messages.
  std::string source;
  std::vector<Pattern> patterns;
  std::vector<std::string> unit_ids;

  // Index of the pattern called `name`, or -1.
  int Find(absl::string_view pattern_name) const;
};

// The text of the built-in fastage-38 file (timing/patterns/fastage-38.yaml).
absl::string_view BuiltinFastage38Text();

// Parses a pattern-set file's text. Errors name the file, line and field.
absl::StatusOr<v1::PatternSetFile> ParsePatternSetFile(absl::string_view text, absl::string_view source_name);

// Evaluates every pattern for `units`. Errors name the pattern, the unit and the value: a formula that does not
// parse, a weight outside [0, 1], a weight table naming a unit the rig does not have, duplicate pattern names.
// Values within 1e-9 of [0, 1] (rounding in the formulas) are clamped.
absl::StatusOr<PatternSet> ResolvePatternSet(const v1::PatternSetFile& file, absl::string_view source_name,
                                             const std::vector<UnitRef>& units);

// The rig's pattern set (its `pattern_set` field: the built-in name, or a file relative to `base_dir`), resolved
// against the rig's units.
absl::StatusOr<PatternSet> LoadRigPatternSet(const v1::RigConfig& rig, absl::string_view base_dir);

// "cross" / "parallel".
absl::string_view PolarizationName(v1::Polarization polarization);

}  // namespace stage::timing
