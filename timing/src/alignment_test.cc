// The alignment self-test on frames whose brightness follows the pattern set's physics (each unit adds its light in
// proportion to its weight; parallel light adds specular): aligned takes pass, shifted ones are named by their shift
// (also by 19, which swaps the cross and parallel blocks), blended patterns (a late light node) and a mislabeled
// full-on frame break the signature in their cycles, missing frames are tolerated.
#include "stage/timing/alignment.h"

#include <random>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"

namespace stage::timing {
namespace {

using ::testing::HasSubstr;

struct Fixture {
  PatternSet set;
  Signature signature;
  std::vector<double> pattern_brightness;  // per pattern, above black
};

Fixture Make(uint64_t seed = 1) {
  auto loaded = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(loaded.ok());
  auto set = LoadRigPatternSet(loaded->rig, loaded->base_dir);
  EXPECT_TRUE(set.ok()) << set.status();
  Fixture f;
  f.set = *set;
  auto sig = PatternSignature(f.set);
  EXPECT_TRUE(sig.ok()) << sig.status();
  f.signature = *sig;
  // What each unit gives the camera's mean at full drive: diffuse, and specular for parallel light.
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  const size_t units = f.set.unit_ids.size();
  std::vector<double> diffuse(units), specular(units);
  for (size_t i = 0; i < units; ++i) {
    diffuse[i] = 0.5 + u(rng);
    specular[i] = 0.3 * u(rng) * u(rng);
  }
  for (const Pattern& p : f.set.patterns) {
    double b = 0;
    for (size_t i = 0; i < units; ++i) {
      b += p.weights[i] * (p.polarization == v1::POLARIZATION_PARALLEL ? diffuse[i] + specular[i] : diffuse[i]);
    }
    f.pattern_brightness.push_back(b);
  }
  return f;
}

// Slots [0, slots) showing pattern (k + shift) mod 38, with relative noise.
std::map<int64_t, double> Frames(const Fixture& f, int64_t slots, int shift = 0, double noise = 0.003) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> n(0, noise);
  std::map<int64_t, double> out;
  for (int64_t k = 0; k < slots; ++k)
    out[k] = f.pattern_brightness[static_cast<size_t>((k + shift) % 38)] * (1 + n(rng));
  return out;
}

TEST(AlignmentTest, TheSignatureOfFastage38) {
  const Fixture f = Make();
  EXPECT_EQ(f.signature.full_on.size(), 2u);           // cross and parallel
  EXPECT_EQ(f.signature.complements.size(), 2u * 9u);  // 3 first-order and 6 second-order pairs per block
  EXPECT_EQ(f.set.patterns[static_cast<size_t>(f.signature.full_on[0])].name, "cross-full");
}

TEST(AlignmentTest, AnAlignedTakePasses) {
  const Fixture f = Make();
  const AlignmentReport r = CheckAlignment(f.signature, 38, Frames(f, 912));
  EXPECT_TRUE(r.ok) << r.message;
  EXPECT_EQ(r.shift, 0);
  EXPECT_EQ(r.cycles_checked, 24);
  EXPECT_LT(r.residual, 0.01);
  EXPECT_THAT(r.message, HasSubstr("aligned"));
}

TEST(AlignmentTest, AShiftedSequenceIsNamedByItsShift) {
  const Fixture f = Make();
  for (int shift : {1, 5, 19, 37}) {
    const AlignmentReport r = CheckAlignment(f.signature, 38, Frames(f, 912, shift));
    EXPECT_FALSE(r.ok) << shift;
    EXPECT_EQ(r.shift, shift) << r.message;
    EXPECT_THAT(r.message, HasSubstr(absl::StrCat("shifted: the frames show the pattern ", shift, " slot(s)")));
    EXPECT_EQ(r.bad_cycles.size(), 24u) << shift;
  }
}

TEST(AlignmentTest, BlendedPatternsBreakTheSignatureWhereTheyHappen) {
  const Fixture f = Make();
  std::map<int64_t, double> frames = Frames(f, 912);
  // A light node late by a third of the exposure from cycle 10 on: each frame mixes in the previous pattern.
  for (int64_t k = 380; k < 912; ++k) {
    frames[k] = 0.67 * f.pattern_brightness[static_cast<size_t>(k % 38)] +
                0.33 * f.pattern_brightness[static_cast<size_t>((k + 37) % 38)];
  }
  const AlignmentReport r = CheckAlignment(f.signature, 38, frames);
  EXPECT_FALSE(r.ok);
  ASSERT_FALSE(r.bad_cycles.empty());
  EXPECT_EQ(r.bad_cycles.front(), 10);
  EXPECT_EQ(r.bad_cycles.size(), 14u);
  EXPECT_THAT(r.message, HasSubstr("signature broken in 14 of 24 cycles (10, 11,"));
}

TEST(AlignmentTest, OneMislabeledFrameIsFoundAndMissingFramesAreTolerated) {
  const Fixture f = Make();
  std::map<int64_t, double> frames = Frames(f, 912);
  // Two frames tagged with each other's slot in cycle 13: its cross full-on and the dim y^2 after it. (Two gradients
  // of about equal brightness could swap unseen: the signature is in the sums, not in each frame.)
  std::swap(frames[494], frames[495]);
  frames.erase(100);                                    // a lost frame in cycle 2: judged on the rest
  for (int64_t k = 800; k < 812; ++k) frames.erase(k);  // cycle 21 mostly gone: not judged
  const AlignmentReport r = CheckAlignment(f.signature, 38, frames);
  EXPECT_FALSE(r.ok);
  EXPECT_EQ(r.shift, 0);
  EXPECT_THAT(r.bad_cycles, ::testing::ElementsAre(13));
  EXPECT_EQ(r.cycles_checked, 23);
}

TEST(AlignmentTest, APatternSetWithoutComplementsCannotBeChecked) {
  PatternSet set;
  set.name = "two";
  set.patterns = {{"full", v1::POLARIZATION_CROSS, {1, 1}}, {"half", v1::POLARIZATION_CROSS, {0.5, 0.2}}};
  auto sig = PatternSignature(set);
  ASSERT_FALSE(sig.ok());
  EXPECT_THAT(sig.status().message(), HasSubstr("no pattern whose complement"));
}

}  // namespace
}  // namespace stage::timing
