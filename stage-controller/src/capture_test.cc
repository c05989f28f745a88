// The capture session in one process: a take against fake camera and light nodes and a fake sync generator, with no
// process, no network and no simulator. The fake generator advances only when the session reads it (a fixed number of
// slots per GetRun) and can hold at a slot until the test lets it go, so every step of a take happens where the test
// says, whatever the machine's load.
#include "capture.h"

#include <atomic>
#include <condition_variable>
#include <filesystem>
#include <map>
#include <mutex>
#include <set>
#include <thread>

#include "absl/strings/str_join.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/timing/timing_tool.h"

namespace stage::controller {
namespace {

using ::testing::HasSubstr;

constexpr int64_t kCycle = 38;
constexpr int64_t kEdgeNs = 1000;       // the fake bus's slot period: T0 is first_slot x this
constexpr int64_t kBus0 = 30 * kCycle;  // where the fake bus's first run starts

// A slot clock that produces `step` edges each time it is read, holds at `hold_at` (a bus slot) until Release, and
// can stop early (its run ends at `stop_at`) or vanish (from `gone_at` on it answers Unavailable).
class FakeGenerator final : public SyncGenerator {
 public:
  struct Run {
    int64_t first = 0, end = 0, current = -1;
  };

  std::string Describe() const override { return "the fake generator"; }
  bool runs_free() const override { return runs_free_; }
  // Like an external generator: its clock runs outside the take's runs, and the run's first edge comes `late_ns`
  // after the planned time (as the witness measures it).
  void RunFree(int64_t late_ns) {
    runs_free_ = true;
    late_ns_ = late_ns;
  }

  absl::StatusOr<SyncRun> Plan(const SyncRunRequest& r, std::chrono::steady_clock::time_point) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (gone_) return absl::UnavailableError("gone");
    int64_t first = std::max<int64_t>(runs_.empty() ? kBus0 : runs_.back().end, r.min_first_slot);
    first = (first + r.align_slots - 1) / r.align_slots * r.align_slots;
    return SyncRun{first, first + r.slots, first * kEdgeNs, first - 1};
  }

  absl::StatusOr<SyncRun> Start(const SyncRunRequest& r, const SyncRun& planned,
                                std::chrono::steady_clock::time_point) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (gone_) return absl::UnavailableError("gone");
    runs_.push_back({planned.first_slot, planned.first_slot + r.slots, planned.first_slot - 1});
    ++starts_;
    SyncRun started = planned;
    started.first_edge_ns += late_ns_;
    return started;
  }

  absl::StatusOr<SyncRun> End(int64_t align) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (gone_) return absl::UnavailableError("gone");
    if (runs_.empty() || runs_.back().current >= runs_.back().end - 1) {
      return absl::FailedPreconditionError("no run");
    }
    Run& run = runs_.back();
    align = std::max<int64_t>(1, align);
    const int64_t next = run.current + 1 - run.first;  // the slot after the one passing now, in the run
    run.end = std::min(run.end, run.first + (next + align - 1) / align * align);
    return ToSync(run);
  }

  absl::StatusOr<SyncRun> GetRun() override {
    std::lock_guard<std::mutex> lock(mu_);
    if (gone_) return absl::UnavailableError("the generator's node is gone");
    if (runs_.empty()) return absl::FailedPreconditionError("no run yet");
    Run& run = runs_.back();
    int64_t next = std::min(run.current + step_, run.end - 1);
    if (hold_at_ >= 0) next = std::min(next, hold_at_);
    if (stop_at_ >= 0 && next >= stop_at_ - 1) {
      next = stop_at_ - 1;
      run.end = std::min(run.end, stop_at_);
    }
    run.current = std::max(run.current, next);
    if (gone_at_ >= 0 && run.current >= gone_at_) gone_ = true;
    changed_.notify_all();
    return ToSync(run);
  }

  // Test controls, in bus slots.
  void HoldAt(int64_t slot) {
    std::lock_guard<std::mutex> lock(mu_);
    hold_at_ = slot;
  }
  void Release() { HoldAt(-1); }
  void StopAt(int64_t slot) {
    std::lock_guard<std::mutex> lock(mu_);
    stop_at_ = slot;
  }
  void GoneAt(int64_t slot) {
    std::lock_guard<std::mutex> lock(mu_);
    gone_at_ = slot;
  }
  // Waits until the current run's clock stands at `slot` (a test deadline only: the generator steps as it is read).
  bool WaitForSlot(int64_t slot) {
    std::unique_lock<std::mutex> lock(mu_);
    return changed_.wait_for(lock, std::chrono::seconds(60),
                             [&] { return !runs_.empty() && runs_.back().current >= slot; });
  }
  // Bus slots that had their edge, over every run.
  bool Produced(int64_t bus_slot) const {
    std::lock_guard<std::mutex> lock(mu_);
    for (const Run& r : runs_) {
      if (bus_slot >= r.first && bus_slot <= r.current && bus_slot < r.end) return true;
    }
    return false;
  }
  std::vector<Run> runs() const {
    std::lock_guard<std::mutex> lock(mu_);
    return runs_;
  }
  int starts() const {
    std::lock_guard<std::mutex> lock(mu_);
    return starts_;
  }

 private:
  static SyncRun ToSync(const Run& r) { return {r.first, r.end, r.first * kEdgeNs, r.current}; }

  mutable std::mutex mu_;
  std::condition_variable changed_;
  std::vector<Run> runs_;
  int64_t step_ = 19, hold_at_ = -1, stop_at_ = -1, gone_at_ = -1;
  bool gone_ = false;
  bool runs_free_ = false;
  int64_t late_ns_ = 0;
  int starts_ = 0;
};

// Brightness of a pattern's frame that satisfies the self-test's signature (each gradient and its complement add up
// to their full-on; parallel full-on brighter than cross).
std::map<int, double> SignatureBrightness(const timing::Signature& s, int cycle) {
  std::map<int, double> b;
  for (int p = 0; p < cycle; ++p) b[p] = 0.5;
  if (s.cross_full >= 0) b[s.cross_full] = 1.0;
  if (s.parallel_full >= 0) b[s.parallel_full] = 2.0;
  for (const auto& [p, q] : s.complements) {
    const int full = s.full_of[p];
    const double f = full >= 0 ? b[full] : 1.0;
    b[p] = 0.4 * f;
    b[q] = 0.6 * f;
  }
  return b;
}

// A camera node whose camera fires at every edge the fake generator produced in its take slots.
class FakeCamera final : public CameraClient {
 public:
  FakeCamera(const FakeGenerator* generator, std::map<int, double> brightness)
      : generator_(generator), brightness_(std::move(brightness)) {}

  absl::Status Arm(const v1::ArmCameraRequest& r, SteadyTime, v1::ArmCameraResponse*) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (refuse_arm_) return absl::UnavailableError("connection refused");
    take_ = r.take_id();
    slots_ = r.slot_count();
    divider_ = std::max<uint32_t>(1, r.trigger_plan().divider());
    phase_ = r.trigger_plan().slot_phase();
    high_speed_ = r.burst();
    return absl::OkStatus();
  }
  absl::Status UpdateTake(const v1::UpdateTakeRequest& r, SteadyTime) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (Gone()) return absl::UnavailableError("connection refused");
    if (r.t0_bus_ns() != 0) {
      first_bus_ = r.t0_bus_ns() / kEdgeNs;
      t0_ = r.t0_bus_ns();
    }
    slots_ = r.slot_count();
    paused_.clear();
    for (const auto& g : r.paused()) paused_.emplace_back(g.first(), g.end());
    return absl::OkStatus();
  }
  int64_t t0() const {
    std::lock_guard<std::mutex> lock(mu_);
    return t0_;
  }
  absl::Status GetStats(v1::CameraStats* stats) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (Gone()) return absl::UnavailableError("connection refused");
    stats->set_take_id(take_);
    stats->set_take_frames_received(static_cast<int64_t>(Fired().size()));
    stats->set_take_frames_written(static_cast<int64_t>(Fired().size()));
    return absl::OkStatus();
  }
  absl::Status GetPreview(const v1::GetPreviewRequest&, v1::Preview*) override {
    return absl::NotFoundError("no preview");
  }
  absl::Status Finish(const v1::FinishCameraRequest& r, std::chrono::milliseconds,
                      v1::CameraTakeReport* report) override {
    std::lock_guard<std::mutex> lock(mu_);
    ++finishes_;
    if (Gone()) return absl::UnavailableError("connection refused");
    uint64_t id = 0;
    for (int64_t k : Fired()) {
      v1::SlotRecord* s = report->add_slots();
      s->set_slot(k);
      s->set_pattern(static_cast<int32_t>(k % kCycle));
      s->set_frame_id(id++);
      if (high_speed_) {
        report->add_brightness_slots(k);
        report->add_brightness(brightness_.at(static_cast<int>(k % kCycle)));
      }
    }
    report->set_frames_written(static_cast<int64_t>(id));
    return absl::OkStatus();
  }

  // From this bus slot on the node is gone (its process died): it refuses every call.
  void GoneAt(int64_t bus_slot) {
    std::lock_guard<std::mutex> lock(mu_);
    gone_at_ = bus_slot;
  }
  void RefuseArm() {
    std::lock_guard<std::mutex> lock(mu_);
    refuse_arm_ = true;
  }
  int finishes() const {
    std::lock_guard<std::mutex> lock(mu_);
    return finishes_;
  }

 private:
  bool Gone() const { return gone_at_ >= 0 && generator_->Produced(gone_at_); }
  // Take slots of this camera whose edge came (before it was gone).
  std::vector<int64_t> Fired() const {
    std::vector<int64_t> out;
    if (first_bus_ < 0) return out;
    for (int64_t k = phase_; k < slots_; k += divider_) {
      bool in_gap = false;
      for (const auto& [a, b] : paused_) in_gap = in_gap || (k >= a && k < b);
      const int64_t bus = first_bus_ + k;
      if (in_gap || (gone_at_ >= 0 && bus >= gone_at_) || !generator_->Produced(bus)) continue;
      out.push_back(k);
    }
    return out;
  }

  const FakeGenerator* generator_;
  std::map<int, double> brightness_;
  mutable std::mutex mu_;
  std::string take_;
  int64_t slots_ = 0, first_bus_ = -1, gone_at_ = -1, t0_ = 0;
  uint32_t divider_ = 1, phase_ = 0;
  bool high_speed_ = false, refuse_arm_ = false;
  int finishes_ = 0;
  std::vector<std::pair<int64_t, int64_t>> paused_;
};

class FakeLight final : public LightClient {
 public:
  absl::Status Arm(const v1::ArmLightRequest& r, SteadyTime, v1::LightStats*) override {
    std::unique_lock<std::mutex> lock(mu_);
    arming_ = true;
    waits_for_start_ = r.start_at_planned_edge();
    changed_.notify_all();
    changed_.wait(lock, [&] { return !hold_arm_; });
    armed_ = true;
    return absl::OkStatus();
  }
  // Arm answers only once Release is called (a slow node), and the test can wait until it is asked.
  void HoldArm() {
    std::lock_guard<std::mutex> lock(mu_);
    hold_arm_ = true;
  }
  void ReleaseArm() {
    std::lock_guard<std::mutex> lock(mu_);
    hold_arm_ = false;
    changed_.notify_all();
  }
  bool WaitUntilAsked() {
    std::unique_lock<std::mutex> lock(mu_);
    return changed_.wait_for(lock, std::chrono::seconds(60), [&] { return arming_; });
  }
  absl::Status Heartbeat(const v1::HeartbeatRequest&, std::chrono::milliseconds, v1::LightStats*) override {
    std::lock_guard<std::mutex> lock(mu_);
    return gone_ ? absl::UnavailableError("connection refused") : absl::OkStatus();
  }
  absl::Status Disarm(const v1::DisarmLightRequest&, SteadyTime, v1::LightStats* stats) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (gone_) return absl::UnavailableError("connection refused");
    armed_ = false;
    if (!blackout_reason_.empty()) stats->set_blackout_reason(blackout_reason_);
    return absl::OkStatus();
  }
  // The node went dark on its own during the take (as its watchdog does): its disarm answers with the reason.
  void BlackOut(const std::string& reason) {
    std::lock_guard<std::mutex> lock(mu_);
    blackout_reason_ = reason;
  }
  absl::Status StartTable(const v1::StartTableRequest& r, SteadyTime) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (refuse_start_) return absl::FailedPreconditionError("its board steps on every edge from arming");
    started_at_.push_back(r.first_edge_ns());
    return absl::OkStatus();
  }
  void RefuseStart() {
    std::lock_guard<std::mutex> lock(mu_);
    refuse_start_ = true;
  }
  std::vector<int64_t> started_at() const {
    std::lock_guard<std::mutex> lock(mu_);
    return started_at_;
  }
  bool waits_for_start() const {
    std::lock_guard<std::mutex> lock(mu_);
    return waits_for_start_;
  }
  void Kill() {
    std::lock_guard<std::mutex> lock(mu_);
    gone_ = true;
  }
  bool armed() const {
    std::lock_guard<std::mutex> lock(mu_);
    return armed_;
  }

 private:
  mutable std::mutex mu_;
  std::condition_variable changed_;
  bool armed_ = false, gone_ = false, hold_arm_ = false, arming_ = false;
  bool refuse_start_ = false, waits_for_start_ = false;
  std::vector<int64_t> started_at_;
  std::string blackout_reason_;
};

// The session owns its clients for a take; the fakes stay with the test, to be looked at after the take.
class CameraRef final : public CameraClient {
 public:
  explicit CameraRef(std::shared_ptr<FakeCamera> c) : c_(std::move(c)) {}
  absl::Status Arm(const v1::ArmCameraRequest& r, SteadyTime t, v1::ArmCameraResponse* a) override {
    return c_->Arm(r, t, a);
  }
  absl::Status UpdateTake(const v1::UpdateTakeRequest& r, SteadyTime t) override { return c_->UpdateTake(r, t); }
  absl::Status GetStats(v1::CameraStats* s) override { return c_->GetStats(s); }
  absl::Status GetPreview(const v1::GetPreviewRequest& r, v1::Preview* p) override { return c_->GetPreview(r, p); }
  absl::Status Finish(const v1::FinishCameraRequest& r, std::chrono::milliseconds d,
                      v1::CameraTakeReport* report) override {
    return c_->Finish(r, d, report);
  }

 private:
  std::shared_ptr<FakeCamera> c_;
};

class LightRef final : public LightClient {
 public:
  explicit LightRef(std::shared_ptr<FakeLight> l) : l_(std::move(l)) {}
  absl::Status Arm(const v1::ArmLightRequest& r, SteadyTime t, v1::LightStats* s) override { return l_->Arm(r, t, s); }
  absl::Status Heartbeat(const v1::HeartbeatRequest& r, std::chrono::milliseconds d, v1::LightStats* s) override {
    return l_->Heartbeat(r, d, s);
  }
  absl::Status Disarm(const v1::DisarmLightRequest& r, SteadyTime t, v1::LightStats* s) override {
    return l_->Disarm(r, t, s);
  }
  absl::Status StartTable(const v1::StartTableRequest& r, SteadyTime t) override { return l_->StartTable(r, t); }

 private:
  std::shared_ptr<FakeLight> l_;
};

class CaptureSessionTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ =
        (std::filesystem::path(::testing::TempDir()) / ::testing::UnitTest::GetInstance()->current_test_info()->name())
            .string();
    std::filesystem::remove_all(root_);
  }
  void TearDown() override {
    if (generator_ != nullptr) generator_->Release();
    {
      std::lock_guard<std::mutex> lock(fakes_mu_);
      for (auto& [id, light] : lights_) light->ReleaseArm();
    }
    if (capture_thread_.joinable()) capture_thread_.join();
  }

  // The shipped rig with two machine-vision cameras and one high-speed camera.
  void Start(v1::NodeFailurePolicy policy = v1::NODE_FAILURE_POLICY_CONTINUE_DEGRADED) {
    auto loaded = LoadRig("builtin:fastage");
    ASSERT_TRUE(loaded.ok()) << loaded.status();
    auto* cams = loaded->rig.mutable_cameras();
    v1::RigConfig kept;
    for (const auto& c : *cams) {
      if (c.id() == "mv-01" || c.id() == "mv-02" || c.id() == "hs-1") *kept.add_cameras() = c;
    }
    *cams = kept.cameras();
    ASSERT_EQ(loaded->rig.cameras_size(), 3);
    loaded->rig.mutable_controller()->set_node_failure_policy(policy);
    loaded->rig.mutable_controller()->set_take_stall_s(60);
    auto report = timing::CheckTiming(*loaded, v1::TimingQuery());
    ASSERT_TRUE(report.ok()) << report.status();
    ASSERT_EQ(report->errors(), 0);
    auto patterns = timing::LoadRigPatternSet(loaded->rig, loaded->base_dir);
    ASSERT_TRUE(patterns.ok());
    auto signature = timing::PatternSignature(*patterns);
    ASSERT_TRUE(signature.ok());
    const std::map<int, double> brightness = SignatureBrightness(*signature, kCycle);

    CaptureDevices devices;
    auto generator = std::make_unique<FakeGenerator>();
    if (free_running_late_ns_ >= 0) generator->RunFree(free_running_late_ns_);
    generator_ = generator.get();
    devices.generator = std::move(generator);
    devices.nodes.camera = [this, brightness](const v1::CameraConfig& c) -> std::unique_ptr<CameraClient> {
      auto cam = std::make_shared<FakeCamera>(generator_, brightness);
      std::lock_guard<std::mutex> lock(fakes_mu_);
      cameras_[c.id()] = cam;
      if (c.id() == camera_gone_) cam->GoneAt(camera_gone_at_);
      if (c.id() == camera_refuses_) cam->RefuseArm();
      return std::make_unique<CameraRef>(cam);
    };
    devices.nodes.light = [this](const v1::LightNodeConfig& n) -> std::unique_ptr<LightClient> {
      auto light = std::make_shared<FakeLight>();
      if (n.id() == slow_light_) light->HoldArm();
      if (n.id() == light_refuses_start_) light->RefuseStart();
      if (n.id() == light_dark_) light->BlackOut(light_dark_reason_);
      std::lock_guard<std::mutex> lock(fakes_mu_);
      lights_[n.id()] = light;
      return std::make_unique<LightRef>(light);
    };
    CaptureOptions options;
    options.take_root = root_;
    options.drain_ms = 100;
    options.poll_interval_ms = 2;
    auto capturer = Capturer::Create(*loaded, report->schedule(), 0, options, std::move(devices));
    ASSERT_TRUE(capturer.ok()) << capturer.status();
    capturer_ = std::move(*capturer);
  }

  // Records every state the session announces.
  CaptureEventFn Recorder() {
    return [this](const v1::CaptureEvent& e) {
      std::lock_guard<std::mutex> lock(events_mu_);
      if (e.state() != v1::SESSION_STATE_UNSPECIFIED) states_.push_back(e.state());
      if (!e.message().empty()) messages_.push_back(e.message());
    };
  }
  std::vector<v1::SessionState> states() {
    std::lock_guard<std::mutex> lock(events_mu_);
    return states_;
  }

  // Captures `frames` on a thread of its own (the test pauses or aborts meanwhile).
  void CaptureInBackground(int64_t frames) {
    capture_thread_ = std::thread([this, frames] {
      v1::CaptureRequest request;
      request.set_frames(frames);
      result_ = capturer_->Capture(request, Recorder());
    });
  }
  absl::StatusOr<v1::TakeSummary> Join() {
    capture_thread_.join();
    return result_;
  }

  std::vector<v1::LedgerEntry> Ledger(const std::string& take_id) {
    v1::GetLedgerRequest request;
    request.set_take_id(take_id);
    request.set_page_size(10000);
    auto page = capturer_->GetLedger(request);
    EXPECT_TRUE(page.ok()) << page.status();
    return page.ok() ? std::vector<v1::LedgerEntry>(page->entries().begin(), page->entries().end())
                     : std::vector<v1::LedgerEntry>{};
  }

  void ExpectEveryNodeDone() {
    for (const auto& [id, light] : lights_) EXPECT_FALSE(light->armed()) << id << " is left armed";
    for (const auto& [id, cam] : cameras_) EXPECT_EQ(cam->finishes(), 1) << id;
    EXPECT_EQ(capturer_->state(), v1::SESSION_STATE_IDLE);
  }

  std::string root_;
  std::unique_ptr<Capturer> capturer_;
  FakeGenerator* generator_ = nullptr;
  std::map<std::string, std::shared_ptr<FakeCamera>> cameras_;
  std::map<std::string, std::shared_ptr<FakeLight>> lights_;
  std::string camera_gone_, camera_refuses_, slow_light_, light_refuses_start_;
  std::string light_dark_, light_dark_reason_;  // a light node that goes dark during the take, and why
  std::mutex fakes_mu_;                         // the session makes its clients (and the fakes) on its own thread
  int64_t camera_gone_at_ = -1;
  int64_t free_running_late_ns_ = -1;  // >= 0: the generator runs free, its first edge this late
  std::thread capture_thread_;
  absl::StatusOr<v1::TakeSummary> result_;
  std::mutex events_mu_;
  std::vector<v1::SessionState> states_;
  std::vector<std::string> messages_;
};

TEST_F(CaptureSessionTest, ATakeRunsThroughEveryStateAndEndsComplete) {
  Start();
  v1::CaptureRequest request;
  request.set_frames(4);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_COMPLETE) << summary->hint();
  // mv cameras: one frame per cycle; hs-1: every slot.
  EXPECT_EQ(summary->total().expected(), 4 + 4 + 4 * kCycle);
  EXPECT_EQ(summary->total().stored(), summary->total().expected());
  ASSERT_EQ(summary->alignment_size(), 1);
  EXPECT_TRUE(summary->alignment(0).ok()) << summary->alignment(0).message();
  EXPECT_EQ(summary->t0_bus_ns(), generator_->runs().at(0).first * kEdgeNs);
  EXPECT_THAT(states(), ::testing::ElementsAre(v1::SESSION_STATE_CONFIGURING, v1::SESSION_STATE_ARMED,
                                               v1::SESSION_STATE_CAPTURING, v1::SESSION_STATE_FINALIZING,
                                               v1::SESSION_STATE_IDLE));
  ExpectEveryNodeDone();
  EXPECT_EQ(Ledger(summary->take_id()).size(), static_cast<size_t>(summary->total().expected()));
}

// An external generator's clock runs free: every light waits for the take's first edge, which the controller names
// before the run; the cameras' T0 is the edge as the witness measured it.
TEST_F(CaptureSessionTest, AFreeRunningClockStartsEveryLightAtThePlannedEdgeAndTheCamerasAtTheMeasuredOne) {
  free_running_late_ns_ = 300;
  Start();
  v1::CaptureRequest request;
  request.set_frames(3);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  const int64_t planned_t0 = generator_->runs().at(0).first * kEdgeNs;
  EXPECT_EQ(summary->t0_bus_ns(), planned_t0 + 300);
  ASSERT_EQ(lights_.size(), 6u);
  for (const auto& [id, light] : lights_) {
    EXPECT_TRUE(light->waits_for_start()) << id;
    EXPECT_THAT(light->started_at(), ::testing::ElementsAre(planned_t0)) << id;
  }
  for (const auto& [id, cam] : cameras_) EXPECT_EQ(cam->t0(), planned_t0 + 300) << id;
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, ALightThatCannotStartAtThePlannedEdgeKeepsAFreeRunningTakeFromRunning) {
  free_running_late_ns_ = 0;
  light_refuses_start_ = "lights-modbus-2";
  Start();
  v1::CaptureRequest request;
  request.set_frames(3);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_EQ(generator_->starts(), 0);
  std::lock_guard<std::mutex> lock(events_mu_);
  EXPECT_THAT(absl::StrJoin(messages_, "\n"),
              ::testing::HasSubstr("lights-modbus-2 could not start its table at the take's first edge"));
}

TEST_F(CaptureSessionTest, ArmedThenCapturedAsArmed) {
  Start();
  v1::CaptureRequest request;
  request.set_frames(2);
  auto armed = capturer_->Arm(request, Recorder());
  ASSERT_TRUE(armed.ok()) << armed.status();
  EXPECT_EQ(capturer_->state(), v1::SESSION_STATE_ARMED);
  EXPECT_EQ(generator_->starts(), 0);  // nothing runs until Capture
  request.set_frames(3);
  EXPECT_THAT(capturer_->Capture(request, nullptr).status().message(), HasSubstr("is armed for 2 frames, not 3"));
  request.set_frames(0);
  auto summary = capturer_->Capture(request, nullptr);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->take_id(), armed->take_id());
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_COMPLETE) << summary->hint();
}

TEST_F(CaptureSessionTest, PauseStopsAtAFrameBoundaryAndResumeLeavesAGap) {
  Start();
  generator_->HoldAt(kBus0 + 50);  // the take's first run starts at kBus0
  CaptureInBackground(4);
  ASSERT_TRUE(generator_->WaitForSlot(kBus0 + 50));
  EXPECT_THAT(capturer_->Resume().status().message(), HasSubstr("not paused"));
  auto paused = capturer_->Pause();
  ASSERT_TRUE(paused.ok()) << paused.status();
  EXPECT_EQ(paused->slot(), 2 * kCycle);  // the next frame boundary after slot 50
  EXPECT_EQ(capturer_->state(), v1::SESSION_STATE_PAUSED);
  EXPECT_THAT(capturer_->Pause().status().message(), HasSubstr("not capturing"));
  generator_->Release();
  ASSERT_TRUE(generator_->WaitForSlot(kBus0 + 2 * kCycle - 1));
  auto resumed = capturer_->Resume();
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_EQ(resumed->slot() % kCycle, 0);
  EXPECT_GE(resumed->slot(), 3 * kCycle);  // a gap of a frame at least
  auto summary = Join();
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_COMPLETE) << summary->hint();
  ASSERT_EQ(summary->paused_size(), 1);
  EXPECT_EQ(summary->paused(0).first(), 2 * kCycle);
  EXPECT_EQ(summary->paused(0).end(), resumed->slot());
  // Four frames of every camera, all stored; the gap's slots are paused, not lost.
  EXPECT_EQ(summary->total().expected(), 4 + 4 + 4 * kCycle);
  EXPECT_EQ(summary->total().stored(), summary->total().expected());
  EXPECT_EQ(summary->total().paused(), (resumed->slot() - 2 * kCycle) / kCycle * (2 + kCycle));
  ASSERT_EQ(generator_->runs().size(), 2u);
  EXPECT_EQ(generator_->runs()[1].first - generator_->runs()[0].first, resumed->slot());
  EXPECT_THAT(states(),
              ::testing::ElementsAre(v1::SESSION_STATE_CONFIGURING, v1::SESSION_STATE_ARMED,
                                     v1::SESSION_STATE_CAPTURING, v1::SESSION_STATE_PAUSED, v1::SESSION_STATE_CAPTURING,
                                     v1::SESSION_STATE_FINALIZING, v1::SESSION_STATE_IDLE));
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, AbortEndsTheRunAtTheNextSlotAndKeepsWhatWasRecorded) {
  Start();
  generator_->HoldAt(kBus0 + 60);
  CaptureInBackground(4);
  ASSERT_TRUE(generator_->WaitForSlot(kBus0 + 60));
  auto aborted = capturer_->Abort();
  ASSERT_TRUE(aborted.ok()) << aborted.status();
  EXPECT_EQ(aborted->slot(), 61);
  generator_->Release();
  auto summary = Join();
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_TRUE(summary->aborted());
  EXPECT_THAT(summary->hint(), HasSubstr("aborted by the operator at slot 61"));
  EXPECT_EQ(summary->slots(), 61);
  EXPECT_EQ(summary->total().stored(), summary->total().expected());  // what ran is all there
  EXPECT_EQ(summary->total().expected(), 2 + 2 + 61);
  EXPECT_EQ(states().back(), v1::SESSION_STATE_IDLE);
  EXPECT_THAT(states(), ::testing::Contains(v1::SESSION_STATE_ABORTING));
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, TwoRequestsCannotBothArm) {
  slow_light_ = "lights-modbus-1";  // the first request's arming waits on it
  Start();
  CaptureInBackground(2);
  std::shared_ptr<FakeLight> slow;
  for (int i = 0; i < 6000 && slow == nullptr; ++i) {
    {
      std::lock_guard<std::mutex> lock(fakes_mu_);  // until the session has made the light's client
      if (lights_.count(slow_light_) > 0) slow = lights_.at(slow_light_);
    }
    if (slow == nullptr) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_NE(slow, nullptr);
  ASSERT_TRUE(slow->WaitUntilAsked());
  v1::CaptureRequest request;
  request.set_frames(1);
  const absl::Status second = capturer_->Capture(request, nullptr).status();
  EXPECT_EQ(second.code(), absl::StatusCode::kFailedPrecondition) << second;
  EXPECT_THAT(capturer_->Arm(request, nullptr).status().message(), HasSubstr("arm: the session is configuring"));
  slow->ReleaseArm();
  auto summary = Join();
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_COMPLETE) << summary->hint();
  EXPECT_EQ(generator_->starts(), 1);
}

TEST_F(CaptureSessionTest, AnArmedTakeAbortedNeverRuns) {
  Start();
  v1::CaptureRequest request;
  request.set_frames(2);
  ASSERT_TRUE(capturer_->Arm(request, nullptr).ok());
  auto aborted = capturer_->Abort();
  ASSERT_TRUE(aborted.ok()) << aborted.status();
  EXPECT_EQ(generator_->starts(), 0);
  auto take = capturer_->GetTake("latest");
  ASSERT_TRUE(take.ok());
  EXPECT_EQ(take->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_THAT(take->hint(), HasSubstr("aborted by the operator before it started"));
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, ACameraLostMidTakeUnderContinueDegraded) {
  camera_gone_ = "mv-02";
  camera_gone_at_ = kBus0 + 80;  // after its frames of cycles 0 and 1
  Start(v1::NODE_FAILURE_POLICY_CONTINUE_DEGRADED);
  v1::CaptureRequest request;
  request.set_frames(4);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_DEGRADED);
  EXPECT_FALSE(summary->aborted());
  EXPECT_EQ(summary->slots(), 4 * kCycle);  // the take ran to its end without it
  for (const v1::LedgerEntry& e : Ledger(summary->take_id())) {
    if (e.camera_id() == "mv-02") {
      EXPECT_EQ(e.reason(), v1::LOSS_REASON_NODE_DOWN) << e.slot();
    } else {
      EXPECT_EQ(e.reason(), v1::LOSS_REASON_STORED) << e.camera_id() << " " << e.slot();
    }
  }
  EXPECT_THAT(summary->hint(), HasSubstr("mv-02 lost 4 (4 node down)"));
}

TEST_F(CaptureSessionTest, ACameraLostMidTakeUnderAbort) {
  camera_gone_ = "mv-02";
  camera_gone_at_ = kBus0 + 80;
  Start(v1::NODE_FAILURE_POLICY_ABORT);
  generator_->HoldAt(kBus0 + 90);  // the clock waits there: the abort, not the take's end, finishes the take
  v1::CaptureRequest request;
  request.set_frames(40);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_TRUE(summary->aborted());
  EXPECT_THAT(summary->hint(), HasSubstr("(camera mv-02 is lost; controller.node_failure_policy: abort) at slot 91"));
  EXPECT_EQ(summary->slots(), 91);
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, ALightNodeLostMidTakeUnderAbort) {
  Start(v1::NODE_FAILURE_POLICY_ABORT);
  generator_->HoldAt(kBus0 + 40);  // until the abort ends the run
  CaptureInBackground(40);
  ASSERT_TRUE(generator_->WaitForSlot(kBus0 + 40));
  lights_.at("lights-gpio-2")->Kill();
  auto summary = Join();
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_THAT(summary->hint(), HasSubstr("light node lights-gpio-2 is lost"));
  EXPECT_EQ(summary->slots(), 41);
  for (const auto& [id, light] : lights_) {
    if (id != "lights-gpio-2") {
      EXPECT_FALSE(light->armed()) << id;
    }
  }
}

// A light node that went dark during the take (its heartbeat watchdog tripped on a starved host) answers its disarm
// with the reason: the take is degraded and says which node and why, though every frame was stored.
TEST_F(CaptureSessionTest, ALightNodeThatWentDarkDuringTheTakeDegradesItByName) {
  light_dark_ = "lights-gpio-2";
  light_dark_reason_ = "controller heartbeat lost: none for 1000 ms while armed for take t";
  Start();
  v1::CaptureRequest request;
  request.set_frames(2);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->total().stored(), summary->total().expected());
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_DEGRADED);
  EXPECT_THAT(summary->hint(), HasSubstr("lights-gpio-2: went dark during the take (controller heartbeat lost: none "
                                         "for 1000 ms while armed for take t); reset it"));
}

TEST_F(CaptureSessionTest, AGeneratorThatStopsEarlyDeclaresTheRestLost) {
  Start();
  generator_->StopAt(kBus0 + 100);
  v1::CaptureRequest request;
  request.set_frames(4);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_DEGRADED);
  EXPECT_THAT(summary->hint(), HasSubstr("the sync generator was lost: the fake generator ended the run at slot 100"));
  EXPECT_EQ(summary->total().expected(), 4 + 4 + 4 * kCycle);  // the take's every slot is accounted for
  int64_t lost = 0;
  for (const v1::LedgerEntry& e : Ledger(summary->take_id())) {
    if (e.slot() < 100) {
      EXPECT_EQ(e.reason(), v1::LOSS_REASON_STORED) << e.camera_id() << " " << e.slot();
    } else {
      EXPECT_EQ(e.reason(), v1::LOSS_REASON_SYNC_GENERATOR_LOST) << e.camera_id() << " " << e.slot();
      ++lost;
    }
  }
  EXPECT_EQ(lost, summary->total().expected() - summary->total().stored());
  EXPECT_GT(lost, 0);
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, AGeneratorLostUnderAbortFailsTheTake) {
  Start(v1::NODE_FAILURE_POLICY_ABORT);
  generator_->GoneAt(kBus0 + 57);
  v1::CaptureRequest request;
  request.set_frames(4);
  auto summary = capturer_->Capture(request, Recorder());
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_TRUE(summary->aborted());
  EXPECT_THAT(summary->hint(), HasSubstr("the sync generator: the fake generator stopped answering"));
  const int64_t last = generator_->runs().at(0).current - kBus0;  // the last edge it produced
  EXPECT_GE(last, 57);
  EXPECT_LT(last, 4 * kCycle);
  for (const v1::LedgerEntry& e : Ledger(summary->take_id())) {
    if (e.slot() <= last) {
      EXPECT_EQ(e.reason(), v1::LOSS_REASON_STORED) << e.camera_id() << " " << e.slot();
    } else {
      EXPECT_EQ(e.reason(), v1::LOSS_REASON_SYNC_GENERATOR_LOST) << e.camera_id() << " " << e.slot();
      EXPECT_THAT(e.detail(), HasSubstr("stopped answering"));
    }
  }
  ExpectEveryNodeDone();
}

TEST_F(CaptureSessionTest, ANodeNotReadyUnderAbortKeepsTheTakeFromRunning) {
  camera_refuses_ = "hs-1";
  Start(v1::NODE_FAILURE_POLICY_ABORT);
  v1::CaptureRequest request;
  request.set_frames(2);
  auto summary = capturer_->Capture(request, nullptr);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(generator_->starts(), 0);
  EXPECT_EQ(summary->outcome(), v1::TAKE_OUTCOME_FAILED);
  EXPECT_THAT(summary->hint(), HasSubstr("not ready: hs-1 (connection refused)"));
}

TEST_F(CaptureSessionTest, WithoutAGeneratorNothingArmsAndTheErrorSaysWhy) {
  auto loaded = LoadRig("builtin:fastage");
  ASSERT_TRUE(loaded.ok());
  auto report = timing::CheckTiming(*loaded, v1::TimingQuery());
  ASSERT_TRUE(report.ok());
  CaptureDevices devices;
  devices.nodes.camera = [](const v1::CameraConfig&) -> std::unique_ptr<CameraClient> { return nullptr; };
  devices.nodes.light = [](const v1::LightNodeConfig&) -> std::unique_ptr<LightClient> { return nullptr; };
  devices.no_generator = "timing.sync_generator names no light node";
  CaptureOptions options;
  options.take_root = root_;
  auto capturer = Capturer::Create(*loaded, report->schedule(), 0, options, std::move(devices));
  ASSERT_TRUE(capturer.ok()) << capturer.status();
  v1::CaptureRequest request;
  request.set_frames(1);
  EXPECT_EQ((*capturer)->Capture(request, nullptr).status().message(),
            "no sync generator: timing.sync_generator names no light node");
  EXPECT_EQ((*capturer)->state(), v1::SESSION_STATE_IDLE);
}

TEST(CaptureOptionsTest, ValidateNamesTheField) {
  CaptureOptions o;
  o.take_root = "relative/takes";
  EXPECT_THAT(o.Validate().message(), HasSubstr("take_root \"relative/takes\" is not an absolute path"));
  o.take_root = "/takes";
  EXPECT_TRUE(o.Validate().ok());
  o.drain_ms = -1;
  EXPECT_THAT(o.Validate().message(), HasSubstr("drain_ms -1"));
  o.drain_ms = 0;
  o.poll_interval_ms = 0;
  EXPECT_THAT(o.Validate().message(), HasSubstr("poll_interval_ms 0"));
}

TEST(SessionMachineTest, OneGateForEveryChange) {
  SessionMachine m;
  EXPECT_EQ(m.state(), v1::SESSION_STATE_IDLE);
  EXPECT_THAT(m.Transition(v1::SESSION_STATE_CAPTURING).status().message(),
              HasSubstr("cannot go from idle to capturing"));
  EXPECT_EQ(m.state(), v1::SESSION_STATE_IDLE);
  for (v1::SessionState s : {v1::SESSION_STATE_CONFIGURING, v1::SESSION_STATE_ARMED, v1::SESSION_STATE_CAPTURING,
                             v1::SESSION_STATE_PAUSED, v1::SESSION_STATE_CAPTURING, v1::SESSION_STATE_ABORTING,
                             v1::SESSION_STATE_ERROR, v1::SESSION_STATE_CONFIGURING, v1::SESSION_STATE_IDLE}) {
    auto changed = m.Transition(s);
    ASSERT_TRUE(changed.ok()) << changed.status();
    EXPECT_TRUE(*changed);
  }
  auto same = m.Transition(v1::SESSION_STATE_IDLE);
  ASSERT_TRUE(same.ok());
  EXPECT_FALSE(*same);
  EXPECT_FALSE(SessionTransitionAllowed(v1::SESSION_STATE_FINALIZING, v1::SESSION_STATE_CAPTURING));
  EXPECT_FALSE(SessionTransitionAllowed(v1::SESSION_STATE_PAUSED, v1::SESSION_STATE_ARMED));
  EXPECT_TRUE(SessionTransitionAllowed(v1::SESSION_STATE_ARMED, v1::SESSION_STATE_FINALIZING));
}

}  // namespace
}  // namespace stage::controller
