// Camera node logic.
#include "camera_node.h"

#include <algorithm>
#include <chrono>
#include <mutex>
#include <thread>

#include "absl/strings/str_cat.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/timing/trigger_scheduler.h"

namespace stage::camera {

absl::StatusOr<CameraSettings> SettingsFromConfig(const v1::CameraConfig& config) {
  CameraSettings s;
  s.width = config.width();
  s.height = config.height();
  s.pixel_format = stage::PixelFormatName(config.pixel_format());
  if (s.pixel_format.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(), "\": pixel_format is not set"));
  }
  s.frame_rate_hz = config.frame_rate_hz();
  s.exposure_us = config.exposure_us();
  s.gain_db = config.gain_db();
  switch (config.trigger().source()) {
    case v1::TRIGGER_SOURCE_HARDWARE_LINE:
      s.trigger = TriggerMode::kHardware;
      break;
    case v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE:
      s.trigger = TriggerMode::kSoftware;
      break;
    case v1::TRIGGER_SOURCE_FREE_RUN:
      s.trigger = TriggerMode::kFreeRun;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat("camera \"", config.id(), "\": trigger.source is not set"));
  }
  return s;
}

absl::StatusOr<std::unique_ptr<CameraNode>> CameraNode::Create(const v1::CameraConfig& config,
                                                               std::unique_ptr<CameraDevice> device,
                                                               std::string rig_hash) {
  STAGE_ASSIGN_OR_RETURN(CameraSettings settings, SettingsFromConfig(config));
  STAGE_RETURN_IF_ERROR(Annotate(device->Configure(settings), absl::StrCat("camera \"", config.id(), "\"")));
  return std::unique_ptr<CameraNode>(new CameraNode(config, std::move(device), std::move(rig_hash)));
}

CameraNode::CameraNode(v1::CameraConfig config, std::unique_ptr<CameraDevice> device, std::string rig_hash)
    : config_(std::move(config)), device_(std::move(device)), rig_hash_(std::move(rig_hash)) {}

CameraNode::~CameraNode() { (void)device_->Stop(); }

v1::NodeInfo CameraNode::Info() const {
  std::string role = config_.role() == v1::CAMERA_ROLE_HIGH_SPEED ? "high-speed" : "machine-vision";
  return MakeNodeInfo(config_.id(), v1::NODE_KIND_CAMERA, role, device_->Describe().backend, rig_hash_);
}

v1::CameraStats CameraNode::Stats() const {
  v1::CameraStats stats;
  stats.set_frames_completed(frames_completed_.load());
  stats.set_bytes_written(0);  // nothing is recorded before the capture issue
  return stats;
}

void CameraNode::OnFrame(std::shared_ptr<const Frame> frame) {
  frames_completed_.fetch_add(1);
  bytes_received_.fetch_add(frame->data.size());
}

class TriggerSessionImpl final : public TriggerSession {
 public:
  TriggerSessionImpl(CameraNode* node, const v1::TriggerStreamHeader& header, bool stop_device)
      : node_(node),
        header_(header),
        frames_at_start_(node->frames_completed_.load()),
        clock_(header.clock()),
        stop_device_(stop_device),
        scheduler_(
            timing::TriggerSchedulerOptions{.max_late_ns = header.max_late_ns() > 0 ? header.max_late_ns() : 100'000,
                                            .keep_all_leads = header.report_leads(),
                                            .realtime_priority = static_cast<int>(header.realtime_priority())},
            [node](int64_t) { return node->device().Trigger(); }) {}

  void Submit(int64_t slot, int64_t time_ns) override {
    const int64_t controller_ns = header_.t0_unix_ns() + time_ns;
    int64_t node_ns;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      const double dt = static_cast<double>(controller_ns - clock_.at_unix_ns());
      node_ns = controller_ns + clock_.offset_ns() + static_cast<int64_t>(dt * clock_.drift_ppm() * 1e-6);
    }
    scheduler_.Submit(slot, node_ns);
  }

  void UpdateClock(const v1::ClockMapping& clock) override {
    std::lock_guard<std::mutex> lock(mutex_);
    clock_ = clock;
  }

  v1::TriggerReport Finish(const std::string& error) override {
    if (error.empty()) {
      scheduler_.Drain();
    } else {
      scheduler_.Stop();
    }
    const timing::TriggerSchedulerStats stats = scheduler_.stats();
    v1::TriggerReport report;
    report.set_received(stats.received);
    report.set_fired(stats.fired);
    report.set_late(stats.late);
    report.set_missed(stats.missed);
    report.mutable_late_slots()->Assign(stats.late_slots.begin(), stats.late_slots.end());
    report.mutable_missed_slots()->Assign(stats.missed_slots.begin(), stats.missed_slots.end());
    if (!stats.leads_ns.empty()) {
      std::vector<int64_t> sorted = stats.leads_ns;
      std::sort(sorted.begin(), sorted.end());
      report.set_min_lead_ns(sorted.front());
      report.set_median_lead_ns(sorted[sorted.size() / 2]);
    }
    report.set_max_fire_late_ns(stats.max_fire_late_ns);
    if (header_.report_leads()) report.mutable_lead_ns()->Assign(stats.leads_ns.begin(), stats.leads_ns.end());
    report.set_error(error);
    report.set_warning(stats.warning);
    auto log = Logger("camera.triggers");
    const std::string& id = node_->config_.id();
    if (stats.late + stats.missed > 0) {
      log->warn("{}: take {}: {} of {} scheduled triggers not fired ({} late, {} missed)", id, header_.take_id(),
                stats.late + stats.missed, stats.received, stats.late, stats.missed);
    } else {
      log->info("{}: take {}: {} scheduled triggers fired", id, header_.take_id(), stats.fired);
    }
    if (stop_device_) {
      // The last triggers' exposures and readouts may still be under way: give the camera time to deliver a frame
      // for every trigger fired before stopping it, so that stopping loses nothing.
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(2);
      while (node_->frames_completed_.load() - frames_at_start_ < stats.fired &&
             std::chrono::steady_clock::now() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
      (void)node_->device().Stop();
    }
    node_->streaming_.store(false);
    return report;
  }

 private:
  CameraNode* node_;
  v1::TriggerStreamHeader header_;
  uint64_t frames_at_start_;
  std::mutex mutex_;
  v1::ClockMapping clock_;  // guarded by mutex_
  bool stop_device_;
  timing::TriggerScheduler scheduler_;
};

absl::StatusOr<std::unique_ptr<TriggerSession>> CameraNode::BeginTriggerStream(const v1::TriggerStreamHeader& header) {
  if (config_.trigger().source() != v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE) {
    return absl::FailedPreconditionError(
        absl::StrCat("camera \"", config_.id(),
                     "\" is not triggered by scheduled software triggers (its trigger.source "
                     "is ",
                     v1::TriggerSource_Name(config_.trigger().source()), ")"));
  }
  if (streaming_.exchange(true)) {
    return absl::FailedPreconditionError(
        absl::StrCat("camera \"", config_.id(), "\" is already running a stream of scheduled triggers"));
  }
  // The device runs for the stream (until capture control owns it, issue #5). Nothing else starts it, so any error
  // here is a real one.
  absl::Status started = device_->Start(this);
  if (!started.ok()) {
    streaming_.store(false);
    return Annotate(started, absl::StrCat("camera \"", config_.id(), "\""));
  }
  const bool stop_device = true;
  return std::unique_ptr<TriggerSession>(new TriggerSessionImpl(this, header, stop_device));
}

}  // namespace stage::camera
