#include "stage/timing/pattern_set.h"

#include <muParser.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <set>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/common/yaml_proto.h"

extern const char kFastage38PatternYaml[];

namespace stage::timing {
namespace {

// Formulas are evaluated in double precision: a weight a hair outside [0, 1] is rounding, not a mistake.
constexpr double kClampTolerance = 1e-9;

std::string PatternLabel(const v1::PatternDefinition& p, int index) {
  return absl::StrCat("patterns[", index, "] (", p.name().empty() ? "unnamed" : p.name(), ")");
}

// Collects errors as "<file>:<line>:<col>: <path>: <message>".
class Errors {
 public:
  Errors(absl::string_view source, const SourceMap& map) : source_(source), map_(map) {}
  void Add(const std::string& path, const std::string& message) {
    list_.push_back(FormatConfigError(source_, map_.Find(path), path, message));
  }
  absl::Status ToStatus() const {
    if (list_.empty()) return absl::OkStatus();
    std::string text = list_.front();
    if (list_.size() > 1) {
      // Show a handful: a broken formula tends to fail for every unit.
      for (size_t i = 1; i < list_.size() && i < 5; ++i) absl::StrAppend(&text, "\n", list_[i]);
      if (list_.size() > 5) absl::StrAppend(&text, "\n(and ", list_.size() - 5, " more errors)");
    }
    return absl::InvalidArgumentError(text);
  }

 private:
  std::string source_;
  const SourceMap& map_;
  std::vector<std::string> list_;
};

}  // namespace

absl::string_view BuiltinFastage38Text() { return kFastage38PatternYaml; }

absl::string_view PolarizationName(v1::Polarization polarization) {
  switch (polarization) {
    case v1::POLARIZATION_CROSS:
      return "cross";
    case v1::POLARIZATION_PARALLEL:
      return "parallel";
    default:
      return "unspecified";
  }
}

int PatternSet::Find(absl::string_view pattern_name) const {
  for (size_t i = 0; i < patterns.size(); ++i) {
    if (patterns[i].name == pattern_name) return static_cast<int>(i);
  }
  return -1;
}

std::vector<UnitRef> RigUnits(const v1::RigConfig& rig) {
  std::vector<UnitRef> units;
  for (const auto& node : rig.light_nodes()) {
    for (const auto& u : node.units()) {
      const auto& d = u.direction();
      double n = std::sqrt(d.x() * d.x() + d.y() * d.y() + d.z() * d.z());
      if (!(n > 0)) n = 1;  // the rig validator rejects zero directions; stay finite regardless
      units.push_back({u.id(), d.x() / n, d.y() / n, d.z() / n});
    }
  }
  return units;
}

// Structural errors carry the file's line and column; ResolvePatternSet's errors name the pattern and the unit.
absl::StatusOr<v1::PatternSetFile> ParsePatternSetFile(absl::string_view text, absl::string_view source_name) {
  v1::PatternSetFile file;
  SourceMap map;
  STAGE_RETURN_IF_ERROR(ParseYamlToProto(text, source_name, &file, &map));
  Errors errors(source_name, map);
  if (file.name().empty()) errors.Add("name", "required field is missing");
  if (file.patterns().empty()) errors.Add("patterns", "a pattern set needs at least one pattern");
  std::map<std::string, int> seen;
  for (int i = 0; i < file.patterns_size(); ++i) {
    const auto& p = file.patterns(i);
    const std::string path = absl::StrCat("patterns[", i, "]");
    if (p.name().empty()) {
      errors.Add(path + ".name", "required field is missing");
    } else if (auto [it, inserted] = seen.emplace(p.name(), i); !inserted) {
      errors.Add(path + ".name",
                 absl::StrCat("duplicate pattern name \"", p.name(), "\" (also patterns[", it->second, "])"));
    }
    if (p.polarization() == v1::POLARIZATION_UNSPECIFIED) {
      errors.Add(path + ".polarization", "required field is missing (cross or parallel)");
    }
    const bool has_formula = !p.formula().empty();
    const bool has_table = p.weights_size() > 0 || p.has_default_weight();
    if (has_formula == has_table) {
      errors.Add(path, has_formula ? "give either `formula` or `weights`, not both"
                                   : "needs a `formula` or a `weights` table");
    }
    if (p.has_default_weight() && !(p.default_weight() >= 0 && p.default_weight() <= 1)) {
      errors.Add(path + ".default_weight", absl::StrFormat("%g is outside [0, 1]", p.default_weight()));
    }
  }
  STAGE_RETURN_IF_ERROR(errors.ToStatus());
  return file;
}

absl::StatusOr<PatternSet> ResolvePatternSet(const v1::PatternSetFile& file, absl::string_view source_name,
                                             const std::vector<UnitRef>& units) {
  SourceMap no_map;  // the file is parsed already; messages name the pattern and unit instead of a line
  Errors errors(source_name, no_map);
  PatternSet set;
  set.name = file.name();
  set.description = file.description();
  set.source = std::string(source_name);
  std::map<std::string, size_t, std::less<>> unit_index;
  for (size_t i = 0; i < units.size(); ++i) {
    set.unit_ids.push_back(units[i].id);
    unit_index.emplace(units[i].id, i);
  }

  for (int i = 0; i < file.patterns_size(); ++i) {
    const auto& def = file.patterns(i);
    const std::string label = PatternLabel(def, i);
    Pattern pattern{def.name(), def.polarization(), std::vector<double>(units.size(), 0.0)};
    auto check_weight = [&](size_t u, double w, absl::string_view how) {
      if (std::isfinite(w) && w >= -kClampTolerance && w <= 1 + kClampTolerance) {
        pattern.weights[u] = std::clamp(w, 0.0, 1.0);
        return;
      }
      errors.Add(label, absl::StrFormat("unit %s (direction %.6f, %.6f, %.6f): %s gives weight %.9g, outside [0, 1]",
                                        units[u].id, units[u].x, units[u].y, units[u].z, how, w));
    };
    if (!def.formula().empty()) {
      double x = 0, y = 0, z = 0;
      mu::Parser parser;
      try {
        parser.DefineVar("x", &x);
        parser.DefineVar("y", &y);
        parser.DefineVar("z", &z);
        parser.SetExpr(def.formula());
        for (size_t u = 0; u < units.size(); ++u) {
          x = units[u].x;
          y = units[u].y;
          z = units[u].z;
          check_weight(u, parser.Eval(), absl::StrCat("formula \"", def.formula(), "\""));
        }
      } catch (const mu::Parser::exception_type& e) {
        errors.Add(label + ".formula",
                   absl::StrFormat("\"%s\": %s (at character %d)", def.formula(), e.GetMsg(), e.GetPos() + 1));
      }
    } else {
      const double fallback = def.has_default_weight() ? def.default_weight() : 0.0;
      for (size_t u = 0; u < units.size(); ++u) pattern.weights[u] = fallback;
      // Sorted for deterministic messages.
      std::map<std::string, double> table(def.weights().begin(), def.weights().end());
      for (const auto& [id, w] : table) {
        auto it = unit_index.find(id);
        if (it == unit_index.end()) {
          errors.Add(label + ".weights", absl::StrCat("unit \"", id, "\" is not a LED unit of the rig"));
          continue;
        }
        check_weight(it->second, w, "the weights table");
      }
    }
    set.patterns.push_back(std::move(pattern));
  }
  STAGE_RETURN_IF_ERROR(errors.ToStatus());
  return set;
}

absl::StatusOr<PatternSet> LoadRigPatternSet(const v1::RigConfig& rig, absl::string_view base_dir) {
  const std::vector<UnitRef> units = RigUnits(rig);
  if (rig.pattern_set() == kFastage38) {
    const std::string source = "fastage-38.yaml (built in)";
    STAGE_ASSIGN_OR_RETURN(v1::PatternSetFile file, ParsePatternSetFile(BuiltinFastage38Text(), source));
    return ResolvePatternSet(file, source, units);
  }
  std::filesystem::path path(rig.pattern_set());
  if (path.is_relative()) path = std::filesystem::path(std::string(base_dir)) / path;
  STAGE_ASSIGN_OR_RETURN(std::string text, ReadFileToString(path.string(), "pattern-set file"));
  STAGE_ASSIGN_OR_RETURN(v1::PatternSetFile file, ParsePatternSetFile(text, path.string()));
  return ResolvePatternSet(file, path.string(), units);
}

}  // namespace stage::timing
