// The take alignment self-test: see alignment.h.
#include "stage/timing/alignment.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace stage::timing {

absl::StatusOr<Signature> PatternSignature(const PatternSet& set, double tolerance) {
  Signature sig;
  const int n = static_cast<int>(set.patterns.size());
  sig.full_of.assign(static_cast<size_t>(n), -1);
  auto is_full = [&](const Pattern& p) {
    return !p.weights.empty() &&
           std::all_of(p.weights.begin(), p.weights.end(), [&](double w) { return w >= 1 - tolerance; });
  };
  std::map<v1::Polarization, int> full_by_polarization;
  for (int i = 0; i < n; ++i) {
    const Pattern& p = set.patterns[static_cast<size_t>(i)];
    if (is_full(p) && !full_by_polarization.count(p.polarization)) {
      full_by_polarization[p.polarization] = i;
      sig.full_on.push_back(i);
      if (p.polarization == v1::POLARIZATION_CROSS) sig.cross_full = i;
      if (p.polarization == v1::POLARIZATION_PARALLEL) sig.parallel_full = i;
    }
  }
  if (sig.full_on.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("pattern set ", set.name, " has no full-on pattern: the alignment self-test needs one"));
  }
  for (int i = 0; i < n; ++i) {
    auto it = full_by_polarization.find(set.patterns[static_cast<size_t>(i)].polarization);
    if (it != full_by_polarization.end()) sig.full_of[static_cast<size_t>(i)] = it->second;
  }
  for (int i = 0; i < n; ++i) {
    const Pattern& a = set.patterns[static_cast<size_t>(i)];
    const int f = sig.full_of[static_cast<size_t>(i)];
    if (f < 0 || f == i) continue;
    const Pattern& full = set.patterns[static_cast<size_t>(f)];
    for (int j = i + 1; j < n; ++j) {
      const Pattern& b = set.patterns[static_cast<size_t>(j)];
      if (b.polarization != a.polarization || j == f) continue;
      bool sums = a.weights.size() == b.weights.size() && a.weights.size() == full.weights.size();
      for (size_t u = 0; sums && u < a.weights.size(); ++u) {
        sums = std::abs(a.weights[u] + b.weights[u] - full.weights[u]) <= tolerance + 1e-9;
      }
      if (sums) sig.complements.emplace_back(i, j);
    }
  }
  if (sig.complements.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("pattern set ", set.name,
                                                   " has no pattern whose complement it also holds: the alignment "
                                                   "self-test has nothing to check"));
  }
  return sig;
}

namespace {

struct CycleScore {
  bool judged = false;
  bool bad = false;
  double residual = 0;
};

// One cycle under the hypothesis that slot k shows pattern (k + shift) mod cycle.
CycleScore ScoreCycle(const Signature& sig, int cycle, const std::map<int64_t, double>& brightness, int64_t c,
                      int shift, const AlignmentOptions& o) {
  CycleScore out;
  std::vector<double> b(static_cast<size_t>(cycle), NAN);
  int have = 0;
  for (int64_t k = c * cycle; k < (c + 1) * cycle; ++k) {
    auto it = brightness.find(k);
    if (it == brightness.end()) continue;
    b[static_cast<size_t>((k + shift) % cycle)] = it->second;
    ++have;
  }
  if (have < o.min_coverage * cycle) return out;
  double sum = 0, worst = 0;
  int pairs = 0;
  for (auto [i, j] : sig.complements) {
    const int f = sig.full_of[static_cast<size_t>(i)];
    const double bi = b[static_cast<size_t>(i)], bj = b[static_cast<size_t>(j)], bf = b[static_cast<size_t>(f)];
    if (std::isnan(bi) || std::isnan(bj) || std::isnan(bf) || bf <= 0) continue;
    const double r = std::abs(bi + bj - bf) / bf;
    sum += r;
    worst = std::max(worst, r);
    ++pairs;
  }
  if (pairs == 0) return out;
  out.judged = true;
  out.residual = sum / pairs;
  // Full-on is the brightest of its block, and parallel full-on (diffuse and specular) outshines cross full-on
  // (diffuse, and specular only as leakage).
  bool brightest = true;
  for (int p = 0; p < cycle; ++p) {
    const int f = sig.full_of[static_cast<size_t>(p)];
    if (f < 0 || std::isnan(b[static_cast<size_t>(p)]) || std::isnan(b[static_cast<size_t>(f)])) continue;
    if (b[static_cast<size_t>(p)] > b[static_cast<size_t>(f)] * (1 + o.tolerance)) brightest = false;
  }
  if (sig.cross_full >= 0 && sig.parallel_full >= 0) {
    const double cross = b[static_cast<size_t>(sig.cross_full)], parallel = b[static_cast<size_t>(sig.parallel_full)];
    if (!std::isnan(cross) && !std::isnan(parallel) && cross > parallel * (1 + o.tolerance)) brightest = false;
  }
  if (!brightest) out.residual += 1;  // no explanation that breaks the brightest rule should win
  out.bad = !brightest || out.residual > o.tolerance || worst > 3 * o.tolerance;
  return out;
}

}  // namespace

AlignmentReport CheckAlignment(const Signature& signature, int cycle, const std::map<int64_t, double>& brightness,
                               const AlignmentOptions& options) {
  AlignmentReport report;
  if (brightness.empty() || cycle <= 0) {
    report.message = "no frames to check";
    return report;
  }
  const int64_t first = brightness.begin()->first / cycle, last = brightness.rbegin()->first / cycle;
  double best = INFINITY;
  for (int s = 0; s < cycle; ++s) {
    double sum = 0;
    int judged = 0;
    std::vector<int64_t> bad;
    for (int64_t c = first; c <= last; ++c) {
      const CycleScore score = ScoreCycle(signature, cycle, brightness, c, s, options);
      if (!score.judged) continue;
      sum += score.residual;
      ++judged;
      if (score.bad) bad.push_back(c);
    }
    const double residual = judged > 0 ? sum / judged : INFINITY;
    if (s == 0) {
      report.residual = residual;
      report.cycles_checked = judged;
      report.bad_cycles = std::move(bad);
    }
    if (residual < best - 1e-12) {
      best = residual;
      report.shift = s;
    }
  }
  report.best_residual = best;
  if (report.cycles_checked == 0) {
    report.message = "no cycle has enough frames to check";
    return report;
  }
  report.ok = report.shift == 0 && report.bad_cycles.empty();
  if (report.ok) {
    report.message =
        absl::StrFormat("aligned (residual %.2f %%, %d cycles)", 100 * report.residual, report.cycles_checked);
  } else if (report.shift != 0 && report.best_residual <= options.tolerance) {
    report.message = absl::StrFormat(
        "shifted: the frames show the pattern %d slot(s) later than tagged (residual %.2f %% at that shift, %.2f %% "
        "as tagged)",
        report.shift, 100 * report.best_residual, 100 * std::min(report.residual, 9.99));
  } else {
    std::string cycles;
    for (size_t i = 0; i < report.bad_cycles.size() && i < 10; ++i) {
      absl::StrAppend(&cycles, i ? ", " : "", report.bad_cycles[i]);
    }
    if (report.bad_cycles.size() > 10) absl::StrAppend(&cycles, ", ...");
    report.message = absl::StrFormat(
        "signature broken in %d of %d cycles (%s): gradient + complement != full-on (residual %.2f %%); patterns "
        "blended or mislabeled",
        report.bad_cycles.size(), report.cycles_checked, cycles, 100 * std::min(report.residual, 9.99));
  }
  return report;
}

}  // namespace stage::timing
