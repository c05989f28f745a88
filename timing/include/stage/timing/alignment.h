// The take alignment self-test (docs/timing.md#alignment): from the mean brightness of a high-speed camera's frames,
// slot by slot, check that every cycle of patterns shows the signature the pattern set implies (in each polarization
// block full-on is the brightest, and every gradient plus its complement equals full-on, to within the tolerance),
// and find the shift that explains the frames best. A frame tagged with the wrong slot, a light node stepping one
// pattern off, or a node late enough to blend two patterns all break the signature; a shifted sequence is named by
// its shift.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/timing/pattern_set.h"

namespace stage::timing {

// The pattern pairs of a set that add up to one of its full-on patterns (same polarization), and those full-on
// patterns: what the self-test checks. InvalidArgument if the set has no full-on pattern or no complementary pair.
struct Signature {
  std::vector<int> full_on;                      // per polarization block, the full-on pattern
  std::vector<std::pair<int, int>> complements;  // (pattern, complement)
  std::vector<int> full_of;                      // per pattern, the full-on pattern of its polarization, or -1
  // The cross and parallel full-on patterns (-1 if absent): parallel light carries the specular reflection that
  // crossed polarizers block, so parallel full-on is the brighter; this tells the two blocks apart.
  int cross_full = -1, parallel_full = -1;
};
absl::StatusOr<Signature> PatternSignature(const PatternSet& set, double tolerance = 1e-6);

struct AlignmentOptions {
  // Relative tolerance of gradient + complement against full-on (the frames carry noise and quantization).
  double tolerance = 0.03;
  // Cycles with fewer frames than this fraction of the patterns are not judged.
  double min_coverage = 0.9;
};

struct AlignmentReport {
  bool ok = false;
  // The shift s that explains the frames best: the frame of slot k shows pattern (k + s) mod cycle. 0 when aligned.
  int shift = 0;
  // Mean relative residual of the complement sums at shift 0 and at the best shift.
  double residual = 0;
  double best_residual = 0;
  int cycles_checked = 0;
  // Cycles (slot / cycle length) whose signature fails at shift 0, in order.
  std::vector<int64_t> bad_cycles;
  // One line for people: "aligned (residual 0.4 %, 24 cycles)", "shifted by 1 slot ...", "signature broken ...".
  std::string message;
};

// `brightness`: slot -> mean brightness of its frame above black (missing slots are absent); the frame of slot k was
// meant to show pattern k mod `cycle` (cycle = the pattern count).
AlignmentReport CheckAlignment(const Signature& signature, int cycle, const std::map<int64_t, double>& brightness,
                               const AlignmentOptions& options = {});

}  // namespace stage::timing
