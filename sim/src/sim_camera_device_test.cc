// SimCameraDevice: settings are checked, frames come on triggers with counters and timestamps from the clock,
// free run follows the virtual clock.
#include "stage/sim/sim_camera_device.h"

#include <atomic>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::sim {
namespace {

using ::testing::HasSubstr;

class CollectingSink : public camera::FrameSink {
 public:
  void OnFrame(std::shared_ptr<const camera::Frame> frame) override {
    std::lock_guard<std::mutex> lock(mutex_);
    frames_.push_back(std::move(frame));
    cv_.notify_all();
  }
  std::vector<std::shared_ptr<const camera::Frame>> WaitFor(size_t n) {
    std::unique_lock<std::mutex> lock(mutex_);
    cv_.wait_for(lock, std::chrono::seconds(10), [&] { return frames_.size() >= n; });
    return frames_;
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<std::shared_ptr<const camera::Frame>> frames_;
};

camera::CameraSettings Small(camera::TriggerMode mode) {
  return {.width = 8,
          .height = 4,
          .pixel_format = "Mono16",
          .frame_rate_hz = 100,
          .exposure_us = 500,
          .gain_db = 0,
          .trigger = mode};
}

TEST(SimCameraDeviceTest, ChecksSettings) {
  SimClock clock;
  SimCameraDevice cam(&clock, "sn");
  auto s = Small(camera::TriggerMode::kSoftware);
  s.pixel_format = "YUV422";
  EXPECT_THAT(std::string(cam.Configure(s).message()), HasSubstr("pixel format \"YUV422\" is not supported"));
  s = Small(camera::TriggerMode::kSoftware);
  s.exposure_us = 20000;
  EXPECT_THAT(std::string(cam.Configure(s).message()), HasSubstr("exposure 20000 us is not within (0, 10000.000)"));
  EXPECT_FALSE(cam.Start(nullptr).ok());  // not configured
}

TEST(SimCameraDeviceTest, SoftwareTriggerDeliversNumberedFrames) {
  SimClock clock(5000);
  SimCameraDevice cam(&clock, "sn");
  ASSERT_TRUE(cam.Configure(Small(camera::TriggerMode::kSoftware)).ok());
  CollectingSink sink;
  EXPECT_FALSE(cam.Trigger().ok());  // not started
  ASSERT_TRUE(cam.Start(&sink).ok());
  ASSERT_TRUE(cam.Trigger().ok());
  ASSERT_TRUE(cam.Trigger().ok());
  auto frames = sink.WaitFor(2);
  ASSERT_TRUE(cam.Stop().ok());
  ASSERT_EQ(frames.size(), 2u);
  EXPECT_EQ(frames[0]->frame_id, 0u);
  EXPECT_EQ(frames[1]->frame_id, 1u);
  EXPECT_EQ(frames[0]->device_timestamp_ns, 5000);
  EXPECT_EQ(frames[0]->data.size(), 8u * 4 * 2);
  EXPECT_NE(frames[0]->data, frames[1]->data);  // the pattern moves with the counter
}

TEST(SimCameraDeviceTest, FreeRunFollowsTheClock) {
  SimClock clock(0);
  SimCameraDevice cam(&clock, "sn");
  ASSERT_TRUE(cam.Configure(Small(camera::TriggerMode::kFreeRun)).ok());
  CollectingSink sink;
  ASSERT_TRUE(cam.Start(&sink).ok());
  for (int i = 1; i <= 3; ++i) {
    while (clock.sleepers() == 0) std::this_thread::yield();
    clock.AdvanceTo(i * 10'000'000);  // 100 Hz: one period
  }
  auto frames = sink.WaitFor(3);
  ASSERT_TRUE(cam.Stop().ok());
  ASSERT_GE(frames.size(), 3u);
  EXPECT_EQ(frames[0]->device_timestamp_ns, 0);
  EXPECT_EQ(frames[1]->device_timestamp_ns, 10'000'000);
  EXPECT_EQ(frames[2]->device_timestamp_ns, 20'000'000);
  EXPECT_FALSE(cam.Trigger().ok());
}

// A clock that tells when it was interrupted, so a test can hold the acquisition thread until Stop() has done so.
class InterruptSignallingClock final : public Clock {
 public:
  int64_t NowNs() const override { return clock_.NowNs(); }
  bool SleepUntilNs(int64_t t_ns, const std::atomic<bool>& stop) override { return clock_.SleepUntilNs(t_ns, stop); }
  void Interrupt() override {
    clock_.Interrupt();
    interrupted_.store(true);
  }
  bool interrupted() const { return interrupted_.load(); }

 private:
  SimClock clock_;
  std::atomic<bool> interrupted_{false};
};

// Stop() while the free run is delivering a frame: the thread goes back to sleep on the clock only after Stop() has
// interrupted it. That sleep must still end (it once slept for ever: the interrupt had come and gone).
TEST(SimCameraDeviceTest, StopWhileAFrameIsDeliveredDoesNotStrandTheFreeRun) {
  InterruptSignallingClock clock;
  SimCameraDevice cam(&clock, "sn");
  ASSERT_TRUE(cam.Configure(Small(camera::TriggerMode::kFreeRun)).ok());
  class HoldingSink : public camera::FrameSink {
   public:
    explicit HoldingSink(const InterruptSignallingClock* clock) : clock_(clock) {}
    void OnFrame(std::shared_ptr<const camera::Frame>) override {
      delivering_.store(true);
      while (!clock_->interrupted()) std::this_thread::yield();  // held until Stop() has interrupted the clock
    }
    std::atomic<bool> delivering_{false};

   private:
    const InterruptSignallingClock* clock_;
  } sink(&clock);
  ASSERT_TRUE(cam.Start(&sink).ok());  // the first frame is due at once
  while (!sink.delivering_.load()) std::this_thread::yield();
  EXPECT_TRUE(cam.Stop().ok());  // returns only when the acquisition thread has ended
}

}  // namespace
}  // namespace stage::sim
