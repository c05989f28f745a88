// Estimating a node's clock against the controller's from NTP-style four-timestamp exchanges (RFC 5905's on-wire
// protocol). t1: request leaves the controller; t2: it reaches the node; t3: the reply leaves the node; t4: it
// reaches the controller. offset = ((t2 - t1) + (t3 - t4)) / 2 is exact when both directions take equally long; the
// error is at most half the round trip delay = (t4 - t1) - (t3 - t2). Queueing only ever adds delay, so the sample
// with the smallest delay of a burst is the most trustworthy (NTP's clock filter). Over bursts, a weighted line
// through those samples gives the offset now and the drift.
#pragma once

#include <cstdint>
#include <deque>
#include <vector>

namespace stage::timing {

struct SyncSample {
  int64_t t1_ns = 0;  // controller clock
  int64_t t2_ns = 0;  // node clock
  int64_t t3_ns = 0;  // node clock
  int64_t t4_ns = 0;  // controller clock

  int64_t offset_ns() const { return ((t2_ns - t1_ns) + (t3_ns - t4_ns)) / 2; }
  int64_t delay_ns() const { return (t4_ns - t1_ns) - (t3_ns - t2_ns); }
  int64_t mid_ns() const { return t1_ns + (t4_ns - t1_ns) / 2; }
};

struct ClockEstimatorOptions {
  // Bursts kept for the fit.
  int window = 16;
  // A burst whose best delay exceeds this many times the smallest in the window is discarded (a queueing spike).
  double outlier_delay_factor = 4.0;
  // Drift is fitted once the kept bursts span at least this long, ns.
  int64_t min_drift_span_ns = 2'000'000'000;
  // Until then, older samples are trusted only within this much drift (quartz oscillators stay within +-100 ppm).
  double max_drift_ppm = 200;
};

// Each kept sample bounds the truth at its time to within half its round trip; carried to now along the fitted drift
// (two standard errors of the drift times its age added), the intervals intersect where the truth is now: offset_ns
// is the middle of that intersection and uncertainty_ns its half width.
struct ClockEstimate {
  bool valid = false;
  // Node minus controller at `at_ns` (controller clock).
  int64_t offset_ns = 0;
  int64_t at_ns = 0;
  int64_t uncertainty_ns = 0;
  double drift_ppm = 0;
  bool drift_known = false;
  int64_t min_delay_ns = 0;
  int samples = 0;
};

class ClockEstimator {
 public:
  explicit ClockEstimator(ClockEstimatorOptions options = {}) : options_(options) {}

  // One burst of exchanges. Keeps its minimum-delay sample; returns false if the burst was empty, had no sample
  // with a non-negative delay, or was discarded as an outlier.
  bool AddBurst(const std::vector<SyncSample>& burst);

  ClockEstimate Current() const { return estimate_; }

  // Controller time -> node time with the current estimate (offset and drift).
  int64_t ToNodeNs(int64_t controller_ns) const;
  // Node time -> controller time.
  int64_t ToControllerNs(int64_t node_ns) const;

 private:
  void Refit();

  ClockEstimatorOptions options_;
  std::deque<SyncSample> kept_;  // best sample per burst, oldest first
  int rejected_in_a_row_ = 0;
  ClockEstimate estimate_;
};

}  // namespace stage::timing
