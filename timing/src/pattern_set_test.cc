// Pattern sets: the shipped fastage-38 weights for known directions, and every kind of bad entry named.
#include "stage/timing/pattern_set.h"

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"

namespace stage::timing {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

std::vector<UnitRef> Units() {
  const double s = 1 / std::sqrt(2.0);
  return {{"px", 1, 0, 0}, {"py", 0, 1, 0}, {"pz", 0, 0, 1}, {"mz", 0, 0, -1}, {"diag", s, s, 0}};
}

PatternSet Builtin(const std::vector<UnitRef>& units) {
  auto file = ParsePatternSetFile(BuiltinFastage38Text(), "fastage-38.yaml");
  EXPECT_TRUE(file.ok()) << file.status();
  auto set = ResolvePatternSet(*file, "fastage-38.yaml", units);
  EXPECT_TRUE(set.ok()) << set.status();
  return *set;
}

double W(const PatternSet& set, const std::string& pattern, int unit) {
  int p = set.Find(pattern);
  EXPECT_GE(p, 0) << pattern;
  return p < 0 ? -1 : set.patterns[p].weights[unit];
}

TEST(Fastage38Test, HasThirtyEightPatternsCrossThenParallelWithFullOnFirst) {
  PatternSet set = Builtin(Units());
  EXPECT_EQ(set.name, "fastage-38");
  ASSERT_EQ(set.patterns.size(), 38u);
  for (int i = 0; i < 19; ++i) {
    EXPECT_EQ(set.patterns[i].polarization, v1::POLARIZATION_CROSS) << i;
    EXPECT_EQ(set.patterns[i + 19].polarization, v1::POLARIZATION_PARALLEL) << i;
    // The same pattern in both blocks: names differ only by the prefix.
    EXPECT_EQ(set.patterns[i].name.substr(6), set.patterns[i + 19].name.substr(9)) << i;
  }
  EXPECT_EQ(set.patterns[0].name, "cross-full");
  // Slot 19 is the parallel full-on slot the machine-vision cameras are triggered on (rig defaults rely on it).
  EXPECT_EQ(set.patterns[19].name, "parallel-full");
  for (const char* name : {"full", "x+", "x-", "y+", "y-", "z+", "z-", "xx", "xx-c", "yy", "yy-c", "zz", "zz-c", "xy",
                           "xy-c", "yz", "yz-c", "xz", "xz-c"}) {
    EXPECT_GE(set.Find(std::string("cross-") + name), 0) << name;
    EXPECT_GE(set.Find(std::string("parallel-") + name), 0) << name;
  }
}

TEST(Fastage38Test, WeightsForKnownDirections) {
  PatternSet set = Builtin(Units());
  const int px = 0, py = 1, pz = 2, mz = 3, diag = 4;
  for (const char* pol : {"cross-", "parallel-"}) {
    auto w = [&](const char* name, int unit) { return W(set, std::string(pol) + name, unit); };
    EXPECT_DOUBLE_EQ(w("full", mz), 1.0);
    EXPECT_DOUBLE_EQ(w("x+", px), 1.0);
    EXPECT_DOUBLE_EQ(w("x-", px), 0.0);
    EXPECT_DOUBLE_EQ(w("x+", py), 0.5);
    EXPECT_DOUBLE_EQ(w("y+", py), 1.0);
    EXPECT_DOUBLE_EQ(w("y-", py), 0.0);
    EXPECT_DOUBLE_EQ(w("z+", pz), 1.0);
    EXPECT_DOUBLE_EQ(w("z+", mz), 0.0);
    EXPECT_DOUBLE_EQ(w("z-", mz), 1.0);
    EXPECT_DOUBLE_EQ(w("xx", px), 1.0);
    EXPECT_DOUBLE_EQ(w("xx-c", px), 0.0);
    EXPECT_DOUBLE_EQ(w("yy", px), 0.0);
    EXPECT_DOUBLE_EQ(w("zz", mz), 1.0);
    EXPECT_DOUBLE_EQ(w("zz-c", py), 1.0);
    EXPECT_DOUBLE_EQ(w("xy", px), 0.5);
    EXPECT_NEAR(w("xy", diag), 1.0, 1e-12);
    EXPECT_NEAR(w("xy-c", diag), 0.0, 1e-12);
    EXPECT_NEAR(w("x+", diag), (1 + 1 / std::sqrt(2.0)) / 2, 1e-12);
    EXPECT_NEAR(w("xx", diag), 0.5, 1e-12);
    EXPECT_DOUBLE_EQ(w("yz", pz), 0.5);
    EXPECT_DOUBLE_EQ(w("xz-c", pz), 0.5);
  }
}

// The take alignment self-test relies on it: every gradient plus its complement lights the dome like full-on.
TEST(Fastage38Test, EveryGradientPlusComplementIsFullOnForTheShippedDome) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok()) << rig.status();
  auto set = LoadRigPatternSet(rig->rig, rig->base_dir);
  ASSERT_TRUE(set.ok()) << set.status();
  ASSERT_EQ(set->unit_ids.size(), 168u);
  const std::vector<std::pair<std::string, std::string>> pairs = {{"x+", "x-"},   {"y+", "y-"},   {"z+", "z-"},
                                                                  {"xx", "xx-c"}, {"yy", "yy-c"}, {"zz", "zz-c"},
                                                                  {"xy", "xy-c"}, {"yz", "yz-c"}, {"xz", "xz-c"}};
  for (const char* pol : {"cross-", "parallel-"}) {
    for (const auto& [a, b] : pairs) {
      const auto& wa = set->patterns[set->Find(pol + a)].weights;
      const auto& wb = set->patterns[set->Find(pol + b)].weights;
      for (size_t u = 0; u < wa.size(); ++u) {
        ASSERT_NEAR(wa[u] + wb[u], 1.0, 1e-9) << pol << a << " + " << b << " at unit " << set->unit_ids[u];
        ASSERT_GE(wa[u], 0.0);
        ASSERT_LE(wa[u], 1.0);
      }
    }
  }
}

absl::Status Resolve(const std::string& yaml) {
  auto file = ParsePatternSetFile(yaml, "bad.yaml");
  if (!file.ok()) return file.status();
  return ResolvePatternSet(*file, "bad.yaml", Units()).status();
}

TEST(PatternSetErrorTest, FormulaOutsideZeroOneNamesPatternUnitAndValue) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: ok, polarization: cross, formula: "1"}
  - {name: too-bright, polarization: parallel, formula: "1 + x"}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("bad.yaml"), HasSubstr("patterns[1] (too-bright)"), HasSubstr("unit px"),
                                 HasSubstr("weight 2,"), HasSubstr("outside [0, 1]"), HasSubstr("\"1 + x\"")));
}

TEST(PatternSetErrorTest, NegativeWeightFromFormula) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: grad, polarization: cross, formula: "z"}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("patterns[0] (grad)"), HasSubstr("unit mz"), HasSubstr("weight -1,")));
}

TEST(PatternSetErrorTest, WeightTableValueOutsideRange) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: table, polarization: cross, weights: {px: 0.5, pz: 1.25}}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("patterns[0] (table)"), HasSubstr("unit pz"), HasSubstr("weight 1.25"),
                                 HasSubstr("weights table")));
}

TEST(PatternSetErrorTest, WeightTableNamesUnknownUnit) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: table, polarization: cross, weights: {led-999: 0.5}}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("patterns[0] (table).weights"), HasSubstr("\"led-999\" is not a LED unit")));
}

TEST(PatternSetErrorTest, FormulaThatDoesNotParse) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: broken, polarization: cross, formula: "(1 + x / 2"}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("patterns[0] (broken).formula"), HasSubstr("\"(1 + x / 2\"")));
}

TEST(PatternSetErrorTest, UnknownVariableInFormula) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: w, polarization: cross, formula: "(1 + w) / 2"}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("patterns[0] (w).formula"), HasSubstr("w")));
}

TEST(PatternSetErrorTest, StructuralErrorsCarryLineAndField) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: a, polarization: cross, formula: "1"}
  - {name: a, formula: "1"}
  - {name: both, polarization: cross, formula: "1", weights: {px: 1}}
  - {name: neither, polarization: cross}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(),
              AllOf(HasSubstr("bad.yaml:4:"), HasSubstr("patterns[1].name: duplicate pattern name \"a\""),
                    HasSubstr("patterns[1].polarization: required"), HasSubstr("give either `formula` or `weights`"),
                    HasSubstr("needs a `formula` or a `weights` table")));
}

TEST(PatternSetErrorTest, UnknownKeyIsRejected) {
  absl::Status s = Resolve(R"(name: t
patterns:
  - {name: a, polarization: cross, formula: "1", colour: red}
)");
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.message(), AllOf(HasSubstr("bad.yaml:3:"), HasSubstr("colour")));
}

TEST(PatternSetTest, WeightTableWithDefault) {
  auto file = ParsePatternSetFile(R"(name: t
patterns:
  - {name: spot, polarization: parallel, weights: {pz: 1}, default_weight: 0.25}
)",
                                  "t.yaml");
  ASSERT_TRUE(file.ok()) << file.status();
  auto set = ResolvePatternSet(*file, "t.yaml", Units());
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_EQ(set->patterns[0].weights, (std::vector<double>{0.25, 0.25, 1, 0.25, 0.25}));
}

TEST(PatternSetTest, RigLoadsAPatternFileRelativeToItself) {
  auto dir = std::filesystem::temp_directory_path() / ("fastage-pattern-test-" + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  std::ofstream(dir / "two.yaml") << "name: two\npatterns:\n"
                                     "  - {name: on, polarization: cross, formula: \"1\"}\n"
                                     "  - {name: top, polarization: parallel, formula: \"max(y, 0)\"}\n";
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  rig->rig.set_pattern_set("two.yaml");
  auto set = LoadRigPatternSet(rig->rig, dir.string());
  std::filesystem::remove_all(dir);
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_EQ(set->name, "two");
  ASSERT_EQ(set->patterns.size(), 2u);
  EXPECT_EQ(set->patterns[1].weights.size(), 168u);
}

TEST(PatternSetTest, MissingPatternFileIsNamed) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  rig->rig.set_pattern_set("nowhere.yaml");
  auto set = LoadRigPatternSet(rig->rig, "/nonexistent-dir");
  ASSERT_FALSE(set.ok());
  EXPECT_THAT(set.status().message(), AllOf(HasSubstr("/nonexistent-dir/nowhere.yaml"), HasSubstr("pattern-set file")));
}

}  // namespace
}  // namespace stage::timing
