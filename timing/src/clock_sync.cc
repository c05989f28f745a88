// Clock offset and drift from four-timestamp exchanges.
#include "stage/timing/clock_sync.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace stage::timing {

bool ClockEstimator::AddBurst(const std::vector<SyncSample>& burst) {
  const SyncSample* best = nullptr;
  for (const SyncSample& s : burst) {
    if (s.delay_ns() < 0) continue;  // a clock stepped during the exchange
    if (best == nullptr || s.delay_ns() < best->delay_ns()) best = &s;
  }
  if (best == nullptr) return false;
  if (!kept_.empty()) {
    int64_t min_delay = std::numeric_limits<int64_t>::max();
    for (const SyncSample& s : kept_) min_delay = std::min(min_delay, s.delay_ns());
    if (static_cast<double>(best->delay_ns()) > options_.outlier_delay_factor * static_cast<double>(min_delay) &&
        best->delay_ns() > 20'000) {
      // A queueing spike: skip it, unless the path has really become slower (three in a row). The older samples stay:
      // their weights already favour the faster exchanges.
      if (++rejected_in_a_row_ < 3) return false;
    }
  }
  rejected_in_a_row_ = 0;
  kept_.push_back(*best);
  while (static_cast<int>(kept_.size()) > options_.window) kept_.pop_front();
  Refit();
  return true;
}

void ClockEstimator::Refit() {
  const SyncSample& last = kept_.back();
  ClockEstimate e;
  e.valid = true;
  e.samples = static_cast<int>(kept_.size());
  e.at_ns = last.mid_ns();
  e.min_delay_ns = last.delay_ns();
  // Times and offsets relative to the latest sample.
  std::vector<double> x, y, half;
  for (const SyncSample& s : kept_) {
    x.push_back(static_cast<double>(s.mid_ns() - last.mid_ns()));
    y.push_back(static_cast<double>(s.offset_ns() - last.offset_ns()));
    half.push_back(s.delay_ns() / 2.0);
  }
  const size_t n = kept_.size();
  double slope = 0, intercept = 0, slope_se = 0;
  const int64_t span = last.mid_ns() - kept_.front().mid_ns();
  if (n >= 3 && span >= options_.min_drift_span_ns) {
    // Weighted least squares of offset against time; weight by the inverse square of each sample's error bound.
    double sw = 0, sx = 0, sy = 0, sxx = 0, sxy = 0;
    for (size_t i = 0; i < n; ++i) {
      const double w = 1.0 / ((half[i] + 1000.0) * (half[i] + 1000.0));
      sw += w;
      sx += w * x[i];
      sy += w * y[i];
      sxx += w * x[i] * x[i];
      sxy += w * x[i] * y[i];
    }
    const double den = sw * sxx - sx * sx;
    if (den > 0) {
      slope = (sw * sxy - sx * sy) / den;
      intercept = (sy - slope * sx) / sw;
      double wrr = 0;
      for (size_t i = 0; i < n; ++i) {
        const double r = y[i] - (intercept + slope * x[i]);
        wrr += r * r / ((half[i] + 1000.0) * (half[i] + 1000.0));
      }
      const double sxx_centered = sxx - sx * sx / sw;
      slope_se = sxx_centered > 0 ? std::sqrt(wrr / static_cast<double>(n - 2) / sxx_centered) : 0.0;
      e.drift_ppm = slope * 1e6;
      e.drift_known = true;
    }
  }
  // Each sample says: at its time the truth was within half its round trip of its offset. Carried to now along the
  // fitted drift, with two standard errors of that drift times its age added, every such interval holds the truth
  // now; so does their intersection (Marzullo's idea without the outliers, which AddBurst removed).
  double lo = -std::numeric_limits<double>::max(), hi = std::numeric_limits<double>::max();
  std::vector<double> center(n), width(n);
  for (size_t i = 0; i < n; ++i) {
    center[i] = y[i] - slope * x[i];
    // With the drift fitted, its standard error; before, the largest drift a free-running clock may have.
    const double drift_bound = e.drift_known ? 2 * slope_se : options_.max_drift_ppm * 1e-6;
    width[i] = half[i] + drift_bound * std::abs(x[i]);
    lo = std::max(lo, center[i] - width[i]);
    hi = std::min(hi, center[i] + width[i]);
  }
  double offset, uncertainty;
  if (lo <= hi) {
    offset = (lo + hi) / 2;
    uncertainty = (hi - lo) / 2;
  } else {
    // The intervals disagree (drift the fit does not capture, a step): take the fit, bounded by the tightest
    // interval plus its distance from the fit.
    offset = e.drift_known ? intercept : 0.0;
    uncertainty = std::numeric_limits<double>::max();
    for (size_t i = 0; i < n; ++i) uncertainty = std::min(uncertainty, width[i] + std::abs(center[i] - offset));
  }
  e.offset_ns = last.offset_ns() + static_cast<int64_t>(std::llround(offset));
  e.uncertainty_ns = static_cast<int64_t>(std::llround(uncertainty));
  estimate_ = e;
}

int64_t ClockEstimator::ToNodeNs(int64_t controller_ns) const {
  const double dt = static_cast<double>(controller_ns - estimate_.at_ns);
  return controller_ns + estimate_.offset_ns + static_cast<int64_t>(std::llround(dt * estimate_.drift_ppm * 1e-6));
}

int64_t ClockEstimator::ToControllerNs(int64_t node_ns) const {
  // Invert ToNodeNs: node = c + offset + (c - at) * r  =>  c = (node - offset + at * r) / (1 + r).
  const double r = estimate_.drift_ppm * 1e-6;
  const double c = (static_cast<double>(node_ns - estimate_.offset_ns - estimate_.at_ns)) / (1 + r);
  return estimate_.at_ns + static_cast<int64_t>(std::llround(c));
}

}  // namespace stage::timing
