#include "device_monitor.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <atomic>

namespace stage::controller {
namespace {

using namespace std::chrono_literals;

// Polls `done` for up to 10 s (the readers run on their own threads).
template <typename F>
bool Eventually(F done) {
  for (int i = 0; i < 1000; ++i) {
    if (done()) return true;
    std::this_thread::sleep_for(10ms);
  }
  return done();
}

TEST(DeviceMonitorTest, KeepsTheLastGoodReadBesideTheErrorAndWakesWatchersOnAChangeOfState) {
  std::atomic<int> reads{0};
  std::atomic<bool> fail{false};
  std::atomic<int> changes{0};
  DeviceTarget light{"light-1", v1::NODE_KIND_LIGHT, [&](std::chrono::milliseconds, v1::NodeDevice* d) {
                       ++reads;
                       if (fail) return absl::UnavailableError("connection refused");
                       d->mutable_light()->set_mode(reads < 3 ? v1::LIGHT_MODE_IDLE : v1::LIGHT_MODE_BLACKOUT);
                       d->mutable_light()->set_temperature_c(30 + reads);
                       return absl::OkStatus();
                     }};
  // A node that never answers within its deadline delays only its own reader.
  DeviceTarget hung{"cam-1", v1::NODE_KIND_CAMERA, [](std::chrono::milliseconds, v1::NodeDevice*) {
                      std::this_thread::sleep_for(300ms);
                      return absl::DeadlineExceededError("Deadline Exceeded");
                    }};
  DeviceMonitor monitor({light, hung}, {.interval = 20ms, .timeout = 10ms}, [&] { ++changes; });
  monitor.Start();
  ASSERT_TRUE(Eventually([&] { return monitor.Snapshot()[0].light().mode() == v1::LIGHT_MODE_BLACKOUT; }));
  std::vector<v1::NodeDevice> seen = monitor.Snapshot();
  ASSERT_EQ(seen.size(), 2u);
  EXPECT_EQ(seen[0].id(), "light-1");
  EXPECT_EQ(seen[0].kind(), v1::NODE_KIND_LIGHT);
  EXPECT_GT(seen[0].read_unix_ns(), 0);
  EXPECT_TRUE(seen[0].error().empty());
  EXPECT_EQ(seen[1].id(), "cam-1");
  EXPECT_EQ(seen[1].read_unix_ns(), 0);
  const int changes_before = changes;
  EXPECT_GE(changes_before, 2);  // the first read (no read -> idle) and idle -> blackout
  fail = true;
  ASSERT_TRUE(Eventually([&] { return !monitor.Snapshot()[0].error().empty(); }));
  seen = monitor.Snapshot();
  EXPECT_EQ(seen[0].error(), "connection refused");
  EXPECT_EQ(seen[0].light().mode(), v1::LIGHT_MODE_BLACKOUT);  // the last good read, kept
  EXPECT_GT(changes, changes_before);
  ASSERT_TRUE(Eventually([&] { return monitor.Snapshot()[1].error() == "Deadline Exceeded"; }));
  monitor.Stop();
}

TEST(DeviceMonitorTest, OptionsMustBePositive) {
  EXPECT_TRUE(DeviceMonitorOptions{}.Validate().ok());
  EXPECT_THAT(std::string(DeviceMonitorOptions{.interval = 0ms}.Validate().message()),
              ::testing::HasSubstr("interval"));
  EXPECT_THAT(std::string(DeviceMonitorOptions{.timeout = 0ms}.Validate().message()), ::testing::HasSubstr("timeout"));
}

}  // namespace
}  // namespace stage::controller
