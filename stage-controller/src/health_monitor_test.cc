// HealthMonitor against real gRPC servers on loopback: up, down (nothing listening / server stopped), unreachable
// (a socket that accepts but never answers), and the wrong node at an address.
#include "health_monitor.h"

#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <thread>

#include "camera_node.h"
#include "camera_service.h"
#include "controller_service.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/clock.h"
#include "stage/common/node_clock.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_server.h"
#include "stage/sim/sim_camera_device.h"
#include "stage/timing/timing_tool.h"

namespace stage::controller {
namespace {

using ::testing::HasSubstr;

// A camera node served on a real port.
struct ServedCamera {
  explicit ServedCamera(const std::string& id) {
    auto rig = LoadRig(kBuiltinRigName);
    v1::CameraConfig config = rig->rig.cameras(0);
    config.set_id(id);
    node = std::move(*camera::CameraNode::Create(config, std::make_unique<sim::SimCameraDevice>(&clock, id), ""));
    service = std::make_unique<camera::CameraService>(node.get());
    server = std::move(*RpcServer::Start({.listen = "127.0.0.1:0"}, {service.get()}));
  }
  SimClock clock;
  std::unique_ptr<camera::CameraNode> node;
  std::unique_ptr<camera::CameraService> service;
  std::unique_ptr<RpcServer> server;
};

// A TCP socket that listens but never accepts: connections complete in the kernel and then hear nothing.
struct SilentSocket {
  SilentSocket() {
    fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr));
    listen(fd, 16);
    socklen_t len = sizeof(addr);
    getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
    address = "127.0.0.1:" + std::to_string(ntohs(addr.sin_port));
  }
  ~SilentSocket() { close(fd); }
  int fd;
  std::string address;
};

// A port with nothing listening: bind, read the port, close.
std::string ClosedPortAddress() {
  SilentSocket s;
  return s.address;
}

// Polls the snapshot until `pred` holds for node `index` or 10 s pass.
v1::NodeStatus WaitFor(const HealthMonitor& monitor, size_t index, v1::NodeState state) {
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (std::chrono::steady_clock::now() < deadline) {
    v1::NodeStatus s = monitor.Snapshot()[index];
    if (s.state() == state) return s;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return monitor.Snapshot()[index];
}

HealthMonitorOptions Fast() { return {std::chrono::milliseconds(50), std::chrono::milliseconds(300)}; }

TEST(HealthMonitorTest, ReportsUpWithInfoAndDownWithReason) {
  ServedCamera camera("cam-a");
  std::string closed = ClosedPortAddress();
  HealthMonitor monitor({{"cam-a", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_MACHINE_VISION, camera.server->address()},
                         {"cam-b", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_MACHINE_VISION, closed}},
                        Fast());
  EXPECT_EQ(monitor.Snapshot()[0].state(), v1::NODE_STATE_UNKNOWN);
  monitor.Start();
  v1::NodeStatus up = WaitFor(monitor, 0, v1::NODE_STATE_UP);
  EXPECT_EQ(up.state(), v1::NODE_STATE_UP);
  EXPECT_EQ(up.version(), "0.1.0");
  EXPECT_EQ(up.backend(), "sim");
  EXPECT_EQ(up.pid(), getpid());
  EXPECT_GT(up.rtt_ns(), 0);
  EXPECT_GT(up.last_seen_unix_ns(), 0);
  EXPECT_EQ(up.reason(), "");
  v1::NodeStatus down = WaitFor(monitor, 1, v1::NODE_STATE_DOWN);
  EXPECT_EQ(down.state(), v1::NODE_STATE_DOWN);
  EXPECT_FALSE(down.reason().empty());
  EXPECT_EQ(down.last_seen_unix_ns(), 0);
}

TEST(HealthMonitorTest, NodeThatStopsIsSeenDownAndChangesGeneration) {
  ServedCamera camera("cam-a");
  HealthMonitor monitor({{"cam-a", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_UNSPECIFIED, camera.server->address()}},
                        Fast());
  monitor.Start();
  ASSERT_EQ(WaitFor(monitor, 0, v1::NODE_STATE_UP).state(), v1::NODE_STATE_UP);
  uint64_t generation = monitor.generation();
  camera.server->Shutdown();
  EXPECT_NE(monitor.WaitForChange(generation, std::chrono::seconds(10)), generation);
  v1::NodeStatus down = WaitFor(monitor, 0, v1::NODE_STATE_DOWN);
  EXPECT_EQ(down.state(), v1::NODE_STATE_DOWN);
  // What it knew of the node stays visible while it is down.
  EXPECT_EQ(down.version(), "0.1.0");
}

TEST(HealthMonitorTest, SilentPeerIsUnreachableNotDown) {
  SilentSocket silent;
  HealthMonitor monitor({{"cam-x", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_UNSPECIFIED, silent.address}}, Fast());
  monitor.Start();
  v1::NodeStatus s = WaitFor(monitor, 0, v1::NODE_STATE_UNREACHABLE);
  EXPECT_EQ(s.state(), v1::NODE_STATE_UNREACHABLE);
  // It stays unreachable over later polls (time-outs and failed handshakes alike); it never reads as down.
  for (int i = 0; i < 20; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    EXPECT_EQ(monitor.Snapshot()[0].state(), v1::NODE_STATE_UNREACHABLE) << monitor.Snapshot()[0].reason();
  }
}

TEST(HealthMonitorTest, WrongNodeAtTheAddressIsNotUp) {
  ServedCamera camera("cam-a");
  HealthMonitor monitor({{"cam-z", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_UNSPECIFIED, camera.server->address()}},
                        Fast());
  monitor.Start();
  v1::NodeStatus s = WaitFor(monitor, 0, v1::NODE_STATE_DOWN);
  EXPECT_THAT(s.reason(), HasSubstr("another node answers"));
}

TEST(HealthMonitorTest, StopReturnsPromptly) {
  SilentSocket silent;
  HealthMonitor monitor({{"cam-x", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_UNSPECIFIED, silent.address}}, Fast());
  monitor.Start();
  monitor.Stop();
  monitor.Stop();  // idempotent
  SUCCEED();
}

}  // namespace
}  // namespace stage::controller

namespace stage::controller {
namespace {

// A node clock that is `offset_ns` ahead of the host's CLOCK_REALTIME and runs `drift_ppm` fast.
class SkewedClock final : public Clock {
 public:
  SkewedClock(int64_t offset_ns, double drift_ppm)
      : offset_ns_(offset_ns), drift_ppm_(drift_ppm), start_(host_.NowNs()) {}
  int64_t NowNs() const override {
    const int64_t now = host_.NowNs();
    return now + offset_ns_ + static_cast<int64_t>(static_cast<double>(now - start_) * drift_ppm_ * 1e-6);
  }
  bool SleepUntilNs(int64_t, const std::atomic<bool>&) override { return false; }
  void Interrupt() override {}
  int64_t Offset(int64_t host_ns) const {
    return offset_ns_ + static_cast<int64_t>(static_cast<double>(host_ns - start_) * drift_ppm_ * 1e-6);
  }

 private:
  RealClock host_{RealClock::Kind::kRealtime};
  int64_t offset_ns_;
  double drift_ppm_;
  int64_t start_;
};

// A camera node whose clock is 3 ms ahead and 200 ppm fast: the controller measures both, within its uncertainty, and
// flags the node against a limit tighter than that uncertainty.
TEST(HealthMonitorClockTest, MeasuresOffsetAndDriftAndFlagsTooUncertainClocks) {
  ServedCamera camera("hs-1");
  SkewedClock skewed(3'000'000, 200);
  NodeClockService clock_service(&skewed, "CLOCK_REALTIME", nullptr);
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {camera.service.get(), &clock_service});
  ASSERT_TRUE(server.ok());
  HealthMonitorOptions options{std::chrono::milliseconds(50), std::chrono::milliseconds(500),
                               std::chrono::milliseconds(100), 6};
  NodeTarget tight{"hs-1", v1::NODE_KIND_CAMERA,  v1::CAMERA_ROLE_HIGH_SPEED, (*server)->address(),
                   1,      "a test limit of 1 ns"};
  HealthMonitor monitor({tight}, options);
  monitor.Start();
  v1::ClockStatus clock;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (!clock.drift_known() && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
    clock = monitor.Snapshot()[0].clock();
  }
  monitor.Stop();
  ASSERT_TRUE(clock.measured());
  ASSERT_TRUE(clock.drift_known()) << "drift is fitted over >= 2 s of bursts";
  const int64_t truth = skewed.Offset(clock.last_sync_unix_ns());
  // The estimate is within its own bound of the truth (plus what 200 ppm adds between the fit time and the stamp).
  EXPECT_LE(std::abs(clock.offset_ns() - truth), clock.uncertainty_ns() + 20'000)
      << "offset " << clock.offset_ns() << " truth " << truth << " uncertainty " << clock.uncertainty_ns();
  EXPECT_NEAR(clock.drift_ppm(), 200, 60);
  EXPECT_GT(clock.min_rtt_ns(), 0);
  EXPECT_GE(clock.samples(), 3);
  EXPECT_LE(clock.last_sync_unix_ns(), UnixNowNs());
  EXPECT_EQ(clock.limit_ns(), 1);
  EXPECT_TRUE(clock.flagged());
  EXPECT_EQ(clock.limit_reason(), "a test limit of 1 ns");
}

// A camera on scheduled software triggers cannot fire right without a clock measurement: until it has one (here:
// never, nothing answers) it is flagged; other nodes are merely unmeasured.
TEST(HealthMonitorClockTest, ANodeThatNeedsAMeasurementAndHasNoneIsFlagged) {
  NodeTarget needs{
      "mv-02", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_MACHINE_VISION, ClosedPortAddress(), 70'000, "scheduled", true};
  NodeTarget other{"mv-03", v1::NODE_KIND_CAMERA, v1::CAMERA_ROLE_MACHINE_VISION, ClosedPortAddress(),
                   274'000, "quarter slot"};
  HealthMonitor monitor({needs, other}, {std::chrono::milliseconds(50), std::chrono::milliseconds(200),
                                         std::chrono::milliseconds(100), 2});
  monitor.Start();
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  std::vector<v1::NodeStatus> s = monitor.Snapshot();
  monitor.Stop();
  EXPECT_FALSE(s[0].clock().measured());
  EXPECT_TRUE(s[0].clock().flagged());
  EXPECT_FALSE(s[1].clock().measured());
  EXPECT_FALSE(s[1].clock().flagged());
}

TEST(HealthMonitorClockTest, LimitsFollowTheTriggerMode) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  rig->rig.mutable_cameras(1)->mutable_trigger()->set_source(v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE);
  auto report = timing::CheckTiming(*rig, {});
  ASSERT_TRUE(report.ok());
  std::vector<NodeTarget> targets = TargetsFromRig(rig->rig, &report->schedule());
  // mv-01 on the hardware line: a quarter of 1096.491 us.
  EXPECT_EQ(targets[0].clock_limit_ns, 274'122);
  // mv-02 on scheduled software triggers: half its 141.491 us late slack.
  EXPECT_EQ(targets[1].clock_limit_ns, 70'745);
  EXPECT_TRUE(targets[1].clock_required);
  EXPECT_FALSE(targets[0].clock_required);
  EXPECT_THAT(targets[1].clock_limit_reason, HasSubstr("141.5 us"));
  EXPECT_EQ(targets[27].kind, v1::NODE_KIND_LIGHT);
  EXPECT_EQ(targets[27].clock_limit_ns, 274'122);
  EXPECT_EQ(targets.back().kind, v1::NODE_KIND_PROCESSING_WORKER);
  EXPECT_EQ(targets.back().clock_limit_ns, 0);
}

}  // namespace
}  // namespace stage::controller
