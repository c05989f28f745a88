// Clock estimation from four-timestamp exchanges: offset and drift recovered through asymmetric, bursty delays.
#include "stage/timing/clock_sync.h"

#include <cmath>
#include <random>

#include "gtest/gtest.h"

namespace stage::timing {
namespace {

// A node whose clock runs `drift_ppm` fast and is `offset_ns` ahead at controller time 0, behind a network whose
// forward direction queues (exponential extra delay) more than the return.
struct Network {
  double offset_ns = 2'500'000;
  double drift_ppm = 50;
  double base_delay_ns = 40'000;
  double forward_queue_mean_ns = 150'000;
  double return_queue_mean_ns = 20'000;
  double processing_ns = 5'000;
  std::mt19937_64 rng{42};

  double NodeAt(double controller_ns) const { return controller_ns + offset_ns + controller_ns * drift_ppm * 1e-6; }
  double TrueOffset(double controller_ns) const { return NodeAt(controller_ns) - controller_ns; }

  SyncSample Exchange(double t1) {
    std::exponential_distribution<double> fwd(1.0 / forward_queue_mean_ns), back(1.0 / return_queue_mean_ns);
    const double arrive = t1 + base_delay_ns + fwd(rng);
    const double leave = arrive + processing_ns;
    const double t4 = leave + base_delay_ns + back(rng);
    return {static_cast<int64_t>(t1), static_cast<int64_t>(NodeAt(arrive)), static_cast<int64_t>(NodeAt(leave)),
            static_cast<int64_t>(t4)};
  }
};

TEST(ClockSyncTest, SampleArithmetic) {
  // Node 1000 ns ahead, 100 ns each way, 10 ns in the node.
  SyncSample s{0, 1100, 1110, 210};
  EXPECT_EQ(s.offset_ns(), 1000);
  EXPECT_EQ(s.delay_ns(), 200);
}

TEST(ClockSyncTest, MinimumDelayFilterAndFitRecoverOffsetAndDrift) {
  Network net;
  ClockEstimator estimator;
  double naive_error_sum = 0;
  int naive_count = 0;
  double t = 1e9;
  for (int burst = 0; burst < 20; ++burst, t += 200e6) {
    std::vector<SyncSample> samples;
    for (int i = 0; i < 8; ++i) {
      samples.push_back(net.Exchange(t + i * 300e3));
      naive_error_sum += std::abs(samples.back().offset_ns() - net.TrueOffset(samples.back().mid_ns()));
      ++naive_count;
    }
    estimator.AddBurst(samples);
  }
  ClockEstimate e = estimator.Current();
  ASSERT_TRUE(e.valid);
  EXPECT_EQ(e.samples, 16);  // the window
  ASSERT_TRUE(e.drift_known);
  const double error = std::abs(e.offset_ns - net.TrueOffset(static_cast<double>(e.at_ns)));
  // The estimate is inside its own error bound, and that bound is tight: about half the best round trip.
  EXPECT_LE(error, e.uncertainty_ns);
  EXPECT_LT(e.uncertainty_ns, 80'000);
  EXPECT_NEAR(e.drift_ppm, 50, 10);
  // Taking every sample as it comes (no minimum-delay filter) is several times worse on this path.
  const double naive = naive_error_sum / naive_count;
  EXPECT_GT(naive, 3 * error) << "naive " << naive << " ns, filtered " << error << " ns";
  // Conversions use offset and drift.
  const int64_t later = e.at_ns + 1'000'000'000;
  EXPECT_NEAR(static_cast<double>(estimator.ToNodeNs(later)), net.NodeAt(static_cast<double>(later)),
              e.uncertainty_ns + 20'000);
  EXPECT_NEAR(static_cast<double>(estimator.ToControllerNs(estimator.ToNodeNs(later))), static_cast<double>(later), 2);
}

TEST(ClockSyncTest, DriftNeedsTimeToBeKnown) {
  Network net;
  ClockEstimator estimator;
  for (int burst = 0; burst < 4; ++burst) estimator.AddBurst({net.Exchange(1e9 + burst * 100e6)});
  EXPECT_TRUE(estimator.Current().valid);
  EXPECT_FALSE(estimator.Current().drift_known);  // 300 ms of bursts
}

// Before drift is known, older samples only count within the largest plausible drift: a 40 ppm clock measured
// twice, a second apart, must still be inside the stated bound.
TEST(ClockSyncTest, BeforeDriftIsKnownOldSamplesAreWidenedByTheLargestPlausibleDrift) {
  ClockEstimator estimator;
  auto sample = [](int64_t t, double offset) {
    // 60 us round trip, symmetric: the sample's offset is exact, its bound +-30 us.
    const int64_t o = static_cast<int64_t>(offset);
    return SyncSample{t, t + 30'000 + o, t + 30'000 + o, t + 60'000};
  };
  estimator.AddBurst({sample(1'000'000'000, 0)});
  estimator.AddBurst({sample(2'000'000'000, 40'000)});  // 40 ppm over one second
  ClockEstimate e = estimator.Current();
  ASSERT_FALSE(e.drift_known);
  EXPECT_LE(std::abs(e.offset_ns - 40'000), e.uncertainty_ns) << e.offset_ns << " +- " << e.uncertainty_ns;
  // The newest sample alone bounds it to its round trip: the estimate is never looser than that.
  EXPECT_LE(e.uncertainty_ns, 30'000);
}

TEST(ClockSyncTest, QueueingSpikesAreSkippedButAPersistentlySlowerPathIsAccepted) {
  ClockEstimator estimator;
  auto sample = [](int64_t t, int64_t delay) {
    return SyncSample{t, t + 500 + delay / 2, t + 500 + delay / 2, t + delay};
  };
  EXPECT_TRUE(estimator.AddBurst({sample(1'000'000'000, 50'000)}));
  EXPECT_FALSE(estimator.AddBurst({sample(1'100'000'000, 900'000)}));  // 18x the best so far
  EXPECT_EQ(estimator.Current().samples, 1);
  EXPECT_FALSE(estimator.AddBurst({sample(1'200'000'000, 900'000)}));
  EXPECT_TRUE(estimator.AddBurst({sample(1'300'000'000, 900'000)}));  // third in a row: the path changed
  EXPECT_EQ(estimator.Current().samples, 2);
  EXPECT_EQ(estimator.Current().min_delay_ns, 900'000);
  // A burst with only impossible samples (negative delay: a clock step) changes nothing.
  EXPECT_FALSE(estimator.AddBurst({SyncSample{0, 10, 5'000, 100}}));
  EXPECT_FALSE(estimator.AddBurst({}));
}

}  // namespace
}  // namespace stage::timing
