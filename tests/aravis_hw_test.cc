// The Aravis backend on a physical camera (label hw): skipped, with a message, where none is on this machine's network.
// FASTAGE_HW_CAMERA names one (serial, user id or address), or FASTAGE_HW_DISCOVER=1 takes the first physical camera
// discovery finds (discovery broadcasts on every network of the machine, so never unasked), and
// FASTAGE_HW_FORMAT its pixel format (default Mono8). Settings kept modest (640x480, 10 Hz) so that any machine-vision
// camera takes them.
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <mutex>
#include <string>
#include <thread>

#include "aravis_camera_device.h"
#include "gtest/gtest.h"

namespace stage::camera {
namespace {

class Counter : public FrameSink {
 public:
  void OnFrame(std::shared_ptr<const Frame> frame) override {
    std::lock_guard<std::mutex> lock(mutex_);
    ++frames_;
    if (!frame->incomplete.empty()) ++incomplete_;
    last_id_ = frame->frame_id;
    changed_.notify_all();
  }
  bool WaitFor(int n, std::chrono::seconds timeout) {
    std::unique_lock<std::mutex> lock(mutex_);
    return changed_.wait_for(lock, timeout, [&] { return frames_ >= n; });
  }
  int incomplete() {
    std::lock_guard<std::mutex> lock(mutex_);
    return incomplete_;
  }

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  int frames_ = 0, incomplete_ = 0;
  uint64_t last_id_ = 0;
};

// The camera to test, or why there is none.
std::string PickCamera(std::string* why) {
  if (const char* env = std::getenv("FASTAGE_HW_CAMERA"); env != nullptr && *env != '\0') return env;
  // Discovery broadcasts on every network of the machine: only when asked to (tests keep off the host's networks).
  if (const char* env = std::getenv("FASTAGE_HW_DISCOVER"); env == nullptr || std::string(env) != "1") {
    *why = "no camera named: set FASTAGE_HW_CAMERA to its serial, user id or address, or FASTAGE_HW_DISCOVER=1 to "
           "take the first physical camera discovery finds on this machine's networks";
    return "";
  }
  for (const AravisCameraInfo& c : ListAravisCameras()) {
    if (c.vendor != "Aravis") return c.serial.empty() ? c.id : c.serial;  // Aravis's own fakes are not hardware
  }
  *why = "no physical GigE Vision or USB3 Vision camera found by discovery (set FASTAGE_HW_CAMERA to name one)";
  return "";
}

CameraSettings Modest(TriggerMode trigger) {
  CameraSettings s;
  s.width = 640;
  s.height = 480;
  const char* format = std::getenv("FASTAGE_HW_FORMAT");
  s.pixel_format = format != nullptr && *format != '\0' ? format : "Mono8";
  s.frame_rate_hz = 10;
  s.exposure_us = 5000;
  s.trigger = trigger;
  return s;
}

TEST(AravisHardwareTest, StreamsFreeRunningAndOnSoftwareTriggers) {
  std::string why;
  const std::string device = PickCamera(&why);
  if (device.empty()) GTEST_SKIP() << why;
  auto camera = AravisCameraDevice::Open("hw", device);
  ASSERT_TRUE(camera.ok()) << camera.status();
  ASSERT_TRUE((*camera)->Configure(Modest(TriggerMode::kFreeRun)).ok());
  {
    Counter sink;
    ASSERT_TRUE((*camera)->Start(&sink).ok());
    EXPECT_TRUE(sink.WaitFor(20, std::chrono::seconds(10)));
    ASSERT_TRUE((*camera)->Stop().ok());
    EXPECT_EQ(sink.incomplete(), 0);
  }
  ASSERT_TRUE((*camera)->Configure(Modest(TriggerMode::kSoftware)).ok());
  Counter sink;
  ASSERT_TRUE((*camera)->Start(&sink).ok());
  for (int i = 0; i < 5; ++i) {
    ASSERT_TRUE((*camera)->Trigger().ok());
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  EXPECT_TRUE(sink.WaitFor(5, std::chrono::seconds(5)));
  ASSERT_TRUE((*camera)->Stop().ok());
  const DeviceStats stats = (*camera)->Stats();
  EXPECT_EQ(stats.frames_failed, 0u);
  EXPECT_TRUE(stats.link_up);
}

}  // namespace
}  // namespace stage::camera
