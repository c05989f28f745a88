// The Aravis camera backend over real GigE Vision (GVCP control, GVSP stream) against Aravis's own fake camera
// (arv-fake-gv-camera-0.8), each on its own loopback address. The suite runs in a network namespace it creates
// itself (its own loopback, where it may add 127.0.0.N): nothing reaches the host's network. Every fake camera is
// a child process, ended by its pid.
#include <signal.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <thread>

#include "aravis_camera_device.h"
#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "net_namespace.h"
#include "stage/common/subprocess.h"
#include "test_support.h"

namespace stage::camera {
namespace {

using ::testing::HasSubstr;
using namespace std::chrono_literals;

// Whether this process got its own network namespace (set in main, before any thread exists).
bool g_isolated = false;
std::string g_why_not;

// What a frame said, kept after the frame itself is released (its buffer goes back to the stream's pool at once,
// as the recorder's does once written).
struct Seen {
  uint64_t frame_id;
  int64_t device_timestamp_ns;
  uint32_t width, height;
  size_t bytes;
  bool lent;
  std::string incomplete;
};

class Collector : public FrameSink {
 public:
  void OnFrame(std::shared_ptr<const Frame> frame) override {
    std::lock_guard<std::mutex> lock(mutex_);
    seen_.push_back({frame->frame_id, frame->device_timestamp_ns, frame->width, frame->height,
                     frame->pixels().size(), frame->data.empty() && frame->lent_owner != nullptr, frame->incomplete});
  }
  std::vector<Seen> frames() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return seen_;
  }
  size_t size() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return seen_.size();
  }
  // Waits until `n` frames came, at most `timeout`.
  bool WaitFor(size_t n, std::chrono::milliseconds timeout) const {
    const auto end = std::chrono::steady_clock::now() + timeout;
    while (size() < n) {
      if (std::chrono::steady_clock::now() > end) return false;
      std::this_thread::sleep_for(5ms);
    }
    return true;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<Seen> seen_;
};

// A fake GigE Vision camera process on 127.0.0.`host`, serial FAKE-`host`.
std::unique_ptr<Subprocess> StartFake(int host, int lost_per_mille = 0) {
  SubprocessOptions o;
  o.argv = {"arv-fake-gv-camera-0.8", "-i", "127.0.0." + std::to_string(host), "-s", "FAKE-" + std::to_string(host)};
  if (lost_per_mille > 0) {
    o.argv.push_back("-r");
    o.argv.push_back(std::to_string(lost_per_mille));
  }
  o.stdout_path = o.stderr_path = "/dev/null";
  auto p = Subprocess::Spawn(o);
  if (!p.ok()) {
    ADD_FAILURE() << p.status();
    return nullptr;
  }
  std::this_thread::sleep_for(300ms);  // its sockets bound
  return std::move(*p);
}

CameraSettings Mono(TriggerMode trigger) {
  CameraSettings s;
  s.width = 640;
  s.height = 480;
  s.pixel_format = "Mono8";
  s.exposure_us = 2000;
  s.gain_db = 0;
  s.trigger = trigger;
  s.frame_rate_hz = 50;
  s.packet_size = 1400;
  s.packet_socket = false;  // a loopback camera: no AF_PACKET ring
  s.buffers = 8;
  s.reconnect_max_s = 0.5;
  return s;
}

std::string Value(const std::vector<std::pair<std::string, std::string>>& back, const std::string& name) {
  for (const auto& [n, v] : back) {
    if (n == name) return v;
  }
  return "(not read back)";
}

class AravisTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!g_isolated) GTEST_SKIP() << "no network namespace of its own: " << g_why_not;
  }
};

TEST_F(AravisTest, OpensByAddressOrSerialConfiguresInOrderAndReadsBack) {
  auto fake = StartFake(2);
  ASSERT_NE(fake, nullptr);
  auto by_address = AravisCameraDevice::Open("mv-01", "127.0.0.2");
  ASSERT_TRUE(by_address.ok()) << by_address.status();
  EXPECT_EQ((*by_address)->Describe().backend, "aravis");
  EXPECT_EQ((*by_address)->Describe().serial, "FAKE-2");
  by_address->reset();  // one controller at a time

  auto found = ListAravisCameras();
  bool listed = false;
  for (const AravisCameraInfo& c : found) listed |= c.serial == "FAKE-2" && c.address == "127.0.0.2";
  EXPECT_TRUE(listed) << "discovery did not list FAKE-2 at 127.0.0.2";

  auto device = AravisCameraDevice::Open("mv-01", "FAKE-2");  // by serial number
  ASSERT_TRUE(device.ok()) << device.status();
  CameraSettings s = Mono(TriggerMode::kSoftware);
  s.offset_x = 16;
  s.offset_y = 8;
  s.features = {{"TestBoolean", "true"}};
  ASSERT_TRUE((*device)->Configure(s).ok());
  const auto back = (*device)->ReadBack();
  EXPECT_EQ(Value(back, "PixelFormat"), "Mono8");
  EXPECT_EQ(Value(back, "Width"), "640");
  EXPECT_EQ(Value(back, "Height"), "480");
  EXPECT_EQ(Value(back, "OffsetX"), "16");
  EXPECT_EQ(Value(back, "TriggerSource"), "Software");
  EXPECT_EQ(Value(back, "GevSCPSPacketSize"), "1400");
  EXPECT_EQ(Value(back, "TestBoolean"), "true");
  EXPECT_NEAR(std::stod(Value(back, "ExposureTime")), 2000, 1);
  // SFNC category order: the image format before acquisition control, transport after, the rig's features last.
  auto at = [&](const std::string& name) {
    for (size_t i = 0; i < back.size(); ++i) {
      if (back[i].first == name) return static_cast<int>(i);
    }
    return -1;
  };
  EXPECT_LT(at("PixelFormat"), at("Width"));
  EXPECT_LT(at("Height"), at("ExposureTime"));
  EXPECT_LT(at("TriggerSource"), at("GevSCPSPacketSize"));
  EXPECT_EQ(at("TestBoolean"), static_cast<int>(back.size()) - 1);

  // What the camera lacks or refuses is named: camera, feature, value.
  CameraSettings bad = s;
  bad.pixel_format = "Mono12";
  absl::Status st = (*device)->Configure(bad);
  EXPECT_THAT(st.message(), HasSubstr("camera \"mv-01\" (FAKE-2): feature PixelFormat = Mono12"));
  EXPECT_THAT(st.message(), HasSubstr("BayerRG8"));  // what it has
  bad = s;
  bad.features = {{"NoSuchFeature", "3"}};
  EXPECT_THAT((*device)->Configure(bad).message(),
              HasSubstr("feature NoSuchFeature = 3: the camera has no such feature"));
  bad = s;
  bad.width = 4096;
  EXPECT_THAT((*device)->Configure(bad).message(), HasSubstr("Width"));
  bad = s;
  bad.ptp = true;
  EXPECT_THAT((*device)->Configure(bad).message(), HasSubstr("neither PtpEnable nor GevIEEE1588"));
}

TEST_F(AravisTest, CameraNodeListsTheCamerasDiscoveryFinds) {
  auto fake = StartFake(7);
  ASSERT_NE(fake, nullptr);
  const auto r = stage::testing::RunCommand({"camera-node", "--list", "--json"}, 20s);
  ASSERT_TRUE(r.exit.ok()) << r.exit.Describe() << ": " << r.err;
  const auto listed = nlohmann::json::parse(r.out);
  bool found = false;
  for (const auto& c : listed) {
    found |= c.at("serial") == "FAKE-7" && c.at("address") == "127.0.0.7" && c.at("protocol") == "GigEVision";
  }
  EXPECT_TRUE(found) << r.out;
  const auto table = stage::testing::RunCommand({"camera-node", "--list"}, 20s);
  EXPECT_THAT(table.out, HasSubstr("FAKE-7"));
  EXPECT_THAT(table.out, HasSubstr("127.0.0.7"));
}

TEST_F(AravisTest, AbsentCameraIsNamedWithWhatWasFound) {
  auto fake = StartFake(3);
  ASSERT_NE(fake, nullptr);
  auto device = AravisCameraDevice::Open("mv-07", "NO-SUCH-SERIAL");
  ASSERT_FALSE(device.ok());
  EXPECT_EQ(device.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(device.status().message(), HasSubstr("camera \"mv-07\" (NO-SUCH-SERIAL): cannot open it"));
  EXPECT_THAT(device.status().message(), HasSubstr("at 127.0.0.3"));
}

TEST_F(AravisTest, SoftwareTriggersGiveOneFrameEachWithCountersAndTimestamps) {
  auto fake = StartFake(4);
  ASSERT_NE(fake, nullptr);
  auto device = AravisCameraDevice::Open("mv-01", "127.0.0.4");
  ASSERT_TRUE(device.ok()) << device.status();
  ASSERT_TRUE((*device)->Configure(Mono(TriggerMode::kSoftware)).ok());
  EXPECT_EQ((*device)->Trigger().code(), absl::StatusCode::kFailedPrecondition);  // not started
  Collector sink;
  ASSERT_TRUE((*device)->Start(&sink).ok());
  std::this_thread::sleep_for(200ms);
  EXPECT_EQ(sink.size(), 0u);  // nothing without a trigger
  // The fake camera looks at its trigger register 25 times a second: a trigger each 100 ms gives one frame each.
  constexpr int kTriggers = 8;
  for (int i = 0; i < kTriggers; ++i) {
    ASSERT_TRUE((*device)->Trigger().ok());
    std::this_thread::sleep_for(100ms);
  }
  ASSERT_TRUE(sink.WaitFor(kTriggers, 3s)) << sink.size() << " frames";
  std::this_thread::sleep_for(150ms);
  ASSERT_TRUE((*device)->Stop().ok());
  const auto frames = sink.frames();
  ASSERT_EQ(frames.size(), static_cast<size_t>(kTriggers));
  for (int i = 0; i < kTriggers; ++i) {
    const Seen& f = frames[static_cast<size_t>(i)];
    EXPECT_EQ(f.frame_id, static_cast<uint64_t>(i));
    EXPECT_EQ(f.width, 640u);
    EXPECT_EQ(f.height, 480u);
    EXPECT_EQ(f.bytes, 640u * 480u);
    // The stream's first frame may arrive before Aravis has enlarged its receive buffer (the fake camera sends a
    // frame in one burst): then it is incomplete, and says so.
    if (i > 0) {
      EXPECT_TRUE(f.incomplete.empty()) << i << ": " << f.incomplete;
    }
    EXPECT_TRUE(f.lent);  // lent from the stream's pool, not copied
    if (i > 0) {
      EXPECT_GT(f.device_timestamp_ns, frames[static_cast<size_t>(i) - 1].device_timestamp_ns);
    }
  }
  const DeviceStats stats = (*device)->Stats();
  const uint64_t incomplete = frames[0].incomplete.empty() ? 0 : 1;
  EXPECT_EQ(stats.frames_completed, static_cast<uint64_t>(kTriggers) - incomplete);
  EXPECT_EQ(stats.frames_failed, incomplete);
  EXPECT_TRUE(stats.link_up);
}

TEST_F(AravisTest, LostPacketsGiveIncompleteFramesThatAreCountedNotDropped) {
  auto fake = StartFake(5, /*lost_per_mille=*/3);
  ASSERT_NE(fake, nullptr);
  auto device = AravisCameraDevice::Open("mv-01", "127.0.0.5");
  ASSERT_TRUE(device.ok()) << device.status();
  ASSERT_TRUE((*device)->Configure(Mono(TriggerMode::kFreeRun)).ok());
  Collector sink;
  ASSERT_TRUE((*device)->Start(&sink).ok());
  ASSERT_TRUE(sink.WaitFor(60, 10s)) << sink.size();
  ASSERT_TRUE((*device)->Stop().ok());
  const auto frames = sink.frames();
  size_t incomplete = 0;
  for (const Seen& f : frames) {
    if (!f.incomplete.empty()) {
      ++incomplete;
      // Packets missing when the trailer came, or (the trailer lost) still missing when the frame timed out.
      EXPECT_THAT(f.incomplete, ::testing::AnyOf("missing packets", "timeout: not all packets arrived in time"));
    }
  }
  const DeviceStats stats = (*device)->Stats();
  // 0.3 % of ~220 packets a frame: about half the frames lose one.
  EXPECT_GT(incomplete, 5u);
  EXPECT_LT(incomplete, frames.size());
  EXPECT_GT(stats.packets_missing, 0u);
  // Every buffer the stream closed reached the sink, whole or marked (a buffer whose leader was lost has no id to
  // deliver it by; the frame counter's gap accounts for it). One frame may have been in flight when Stop() came: the
  // stream may count it after the last delivery.
  uint64_t leaderless = 0;
  for (size_t i = 1; i < frames.size(); ++i) leaderless += frames[i].frame_id - frames[i - 1].frame_id - 1;
  const uint64_t closed = stats.frames_completed + stats.frames_failed;
  EXPECT_GE(closed, frames.size() + leaderless);
  EXPECT_LE(closed, frames.size() + leaderless + 1);
  EXPECT_GE(stats.frames_failed, incomplete + leaderless);
  EXPECT_LE(stats.frames_failed, incomplete + leaderless + 1);
}

TEST_F(AravisTest, ACameraKilledAndRestartedIsReconnectedWithItsSettingsAndStreamsAgain) {
  auto fake = StartFake(6);
  ASSERT_NE(fake, nullptr);
  auto device = AravisCameraDevice::Open("mv-01", "127.0.0.6");
  ASSERT_TRUE(device.ok()) << device.status();
  CameraSettings s = Mono(TriggerMode::kFreeRun);
  s.frame_rate_hz = 20;
  ASSERT_TRUE((*device)->Configure(s).ok());
  Collector sink;
  ASSERT_TRUE((*device)->Start(&sink).ok());
  ASSERT_TRUE(sink.WaitFor(10, 5s));
  fake->Signal(SIGKILL);
  fake->Wait();
  const size_t before = sink.size();
  // A new camera process at the same address, in its power-on state (512x512, 25 fps free run).
  fake = StartFake(6);
  ASSERT_NE(fake, nullptr);
  // Aravis sees the loss within its heartbeat retries (~8 s here); the node reconnects and restores the settings.
  const auto deadline = std::chrono::steady_clock::now() + 40s;
  while ((*device)->Stats().reconnects == 0 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(100ms);
  }
  const DeviceStats stats = (*device)->Stats();
  EXPECT_EQ(stats.link_losses, 1u);
  ASSERT_EQ(stats.reconnects, 1u) << stats.link_detail;
  EXPECT_TRUE(stats.link_up);
  EXPECT_THAT(stats.link_detail, HasSubstr("settings restored"));
  ASSERT_TRUE(sink.WaitFor(before + 10, 5s)) << "no frames after reconnecting";
  ASSERT_TRUE((*device)->Stop().ok());
  const auto frames = sink.frames();
  const Seen& last = frames.back();
  EXPECT_EQ(last.width, 640u);  // restored, not the camera's power-on 512
  EXPECT_EQ(last.height, 480u);
  EXPECT_EQ(Value((*device)->ReadBack(), "Width"), "640");
  for (size_t i = 1; i < frames.size(); ++i) EXPECT_GT(frames[i].frame_id, frames[i - 1].frame_id) << i;
}

}  // namespace
}  // namespace stage::camera

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  // Each fake camera needs an address of its own: 127.0.0.2-9 in a network namespace of this process's own.
  stage::camera::g_why_not = stage::testing::IsolateNetwork(2, 9);
  stage::camera::g_isolated = stage::camera::g_why_not.empty();
  return RUN_ALL_TESTS();
}
