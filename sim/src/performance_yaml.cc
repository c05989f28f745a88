#include "stage/sim/performance_yaml.h"

#include <cerrno>
#include <cstring>
#include <fstream>
#include <map>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace stage::sim {

absl::Status WritePerformanceYaml(const Performance& performance, const std::string& path) {
  std::map<double, std::string> starts(performance.sequences.begin(), performance.sequences.end());
  std::string text = "keys:\n";
  for (const auto& [t, pose] : performance.keys) {
    absl::StrAppendFormat(&text, "  - {t: %.17g", t);
    for (int e = 0; e < kExpressionCount; ++e) {
      absl::StrAppendFormat(&text, ", %s: %.9g", ExpressionName(e), pose.expression[static_cast<size_t>(e)]);
    }
    absl::StrAppendFormat(&text, ", yaw: %.9g, pitch: %.9g, roll: %.9g, x: %.9g, y: %.9g, z: %.9g",
                          pose.rotation_deg.x(), pose.rotation_deg.y(), pose.rotation_deg.z(), pose.translation_mm.x(),
                          pose.translation_mm.y(), pose.translation_mm.z());
    if (auto start = starts.find(t); start != starts.end()) {
      absl::StrAppend(&text, ", sequence: \"", start->second, "\"");
      starts.erase(start);
    }
    absl::StrAppend(&text, "}\n");
  }
  if (!starts.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": sequence \"", starts.begin()->second, "\" starts at ",
                                                   starts.begin()->first, " s, between keys"));
  }
  std::ofstream out(path, std::ios::trunc);
  out << text;
  out.close();
  if (!out) return absl::InternalError(absl::StrCat(path, ": cannot write: ", std::strerror(errno)));
  return absl::OkStatus();
}

}  // namespace stage::sim
