// Camera node logic.
#include "camera_node.h"

#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/message_differencer.h>

#include <algorithm>
#include <chrono>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "preview.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/timing/time_base.h"
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
  s.offset_x = config.offset_x();
  s.offset_y = config.offset_y();
  s.binning = std::max<uint32_t>(1, config.binning());
  if (config.has_black_level()) s.black_level = config.black_level();
  s.packet_size = config.packet_size() > 0 ? config.packet_size() : 1500;
  s.packet_delay_ns = config.gige().packet_delay_ns();
  s.ptp = config.gige().ptp();
  s.packet_resend = !config.gige().has_packet_resend() || config.gige().packet_resend();
  s.buffers = config.gige().buffers() > 0 ? config.gige().buffers() : 16;
  s.reconnect_max_s = config.gige().reconnect_max_s() > 0 ? config.gige().reconnect_max_s() : 5;
  if (!config.trigger().line().empty()) s.trigger_line = config.trigger().line();
  s.packet_socket = !config.gige().has_packet_socket() || config.gige().packet_socket();
  // In name order (the rig's map has none of its own): a rig file gives the same sequence every time.
  std::map<std::string, std::string> features(config.features().begin(), config.features().end());
  s.features.assign(features.begin(), features.end());
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
  auto node = std::unique_ptr<CameraNode>(new CameraNode(config, std::move(device), std::move(rig_hash)));
  node->metrics_ =
      metrics::Registry::Default().AddCollector([n = node.get()](metrics::Writer& w) { n->CollectMetrics(w); });
  return node;
}

void CameraNode::CollectMetrics(metrics::Writer& w) const {
  const v1::CameraStats s = Stats();
  const metrics::Labels camera = {{"camera", config_.id()}};
  auto count = [&](const char* name, const char* help, double v) { w.Counter(name, help, camera, v); };
  auto gauge = [&](const char* name, const char* help, double v) { w.Gauge(name, help, camera, v); };
  count("stage_camera_frames_received_total", "Frames the camera delivered complete",
        static_cast<double>(s.frames_completed()));
  count("stage_camera_frames_failed_total", "Frames the camera delivered incomplete or corrupt",
        static_cast<double>(s.frames_failed()));
  count("stage_camera_packets_missing_total", "Stream packets that never arrived (GigE Vision)",
        static_cast<double>(s.packets_missing()));
  count("stage_camera_packets_resent_total", "Stream packets the camera resent on request (GigE Vision)",
        static_cast<double>(s.packets_resent()));
  count("stage_camera_buffer_underruns_total", "Frames the camera had no buffer for",
        static_cast<double>(s.buffer_underruns()));
  count("stage_camera_link_losses_total", "Times control of the camera was lost", static_cast<double>(s.link_losses()));
  gauge("stage_camera_link_up", "1 while the node controls its camera, else 0", s.link_up() ? 1 : 0);
  gauge("stage_camera_frames_owed", "Frames triggered and not delivered yet", static_cast<double>(s.frames_owed()));
  gauge("stage_camera_take_frames_expected", "Frames the take being recorded expects from this camera (0: no take)",
        static_cast<double>(s.take_frames_expected()));
  gauge("stage_camera_take_frames_written", "Frames of the take being recorded written so far",
        static_cast<double>(s.take_frames_written()));
  gauge("stage_camera_take_frames_lost", "Frames of the take being recorded lost so far",
        static_cast<double>(s.take_frames_lost()));
}

CameraNode::CameraNode(v1::CameraConfig config, std::unique_ptr<CameraDevice> device, std::string rig_hash)
    : config_(std::move(config)), device_(std::move(device)), rig_hash_(std::move(rig_hash)) {}

CameraNode::~CameraNode() { (void)device_->Stop(); }

v1::NodeInfo CameraNode::Info() const {
  return MakeNodeInfo(config_.id(), v1::NODE_KIND_CAMERA, config_.role(), device_->Describe().backend, rig_hash_);
}

v1::CameraStats CameraNode::Stats() const {
  v1::CameraStats stats;
  stats.set_frames_completed(frames_completed_.load());
  const DeviceStats d = device_->Stats();
  stats.set_frames_failed(d.frames_failed);
  stats.set_packets_missing(d.packets_missing);
  stats.set_packets_resent(d.packets_resent);
  stats.set_buffer_underruns(d.buffer_underruns);
  stats.set_link_losses(d.link_losses);
  stats.set_reconnects(d.reconnects);
  stats.set_link_up(d.link_up);
  stats.set_link_detail(d.link_detail);
  const DeviceBacklog backlog = device_->Backlog();
  stats.set_frames_owed(backlog.frames_owed);
  stats.set_device_work(backlog.work_done);
  stats.set_device_activity(backlog.activity);
  std::lock_guard<std::mutex> lock(take_mutex_);
  // The armed take, or the one finishing (a burst camera writing what it held).
  const std::shared_ptr<TakeRecorder>& r = recorder_ ? recorder_ : finishing_;
  if (r) {
    stats.set_take_id(recorder_ ? take_id_ : finishing_id_);
    stats.set_take_frames_received(r->frames_received());
    stats.set_take_frames_written(r->frames_written());
    stats.set_take_frames_expected(r->expected_frames());
    stats.set_take_frames_lost(r->frames_lost());
  }
  return stats;
}

void CameraNode::OnFrame(std::shared_ptr<const Frame> frame) {
  frames_completed_.fetch_add(1);
  bytes_received_.fetch_add(frame->pixels().size());
  last_frame_id_.store(static_cast<int64_t>(frame->frame_id));
  std::shared_ptr<TakeRecorder> recorder;
  {
    std::lock_guard<std::mutex> lock(take_mutex_);
    recorder = recorder_;
  }
  if (recorder) recorder->OnFrame(std::move(frame));
}

void CameraNode::OnFrameLost() {
  std::shared_ptr<TakeRecorder> recorder;
  {
    std::lock_guard<std::mutex> lock(take_mutex_);
    recorder = recorder_;
  }
  if (recorder) recorder->OnFrameLost();
}

absl::StatusOr<v1::ArmCameraResponse> CameraNode::Arm(const v1::ArmCameraRequest& request) {
  std::lock_guard<std::mutex> lock(take_mutex_);
  if (recorder_ && take_id_ == request.take_id() && !request.take_id().empty()) {
    // Asked again for the take it is armed for (the controller did not hear the first answer): the same answer.
    v1::ArmCameraResponse response;
    response.set_expected_frames(recorder_->expected_frames());
    response.set_path(recorder_->path());
    return response;
  }
  if (recorder_) {
    return absl::FailedPreconditionError(
        absl::StrCat("camera \"", config_.id(), "\": take ", take_id_, " is armed; finish it first"));
  }
  if (request.take_id().empty()) return absl::InvalidArgumentError("arm: no take id");
  if (request.slot_rate_hz() == 0) return absl::InvalidArgumentError("arm: no slot rate");
  auto base = timing::TimeBase::Create(request.slot_rate_hz());
  if (!base.ok()) return base.status();
  if (request.has_camera()) {
    // The controller's copy of the settings must be what this node's device runs.
    // (Where the node listens is the deployment's, not a setting.)
    google::protobuf::util::MessageDifferencer diff;
    diff.IgnoreField(v1::CameraConfig::descriptor()->FindFieldByName("address"));
    std::string report;
    diff.ReportDifferencesToString(&report);
    if (!diff.Compare(config_, request.camera())) {
      std::vector<std::string> lines = absl::StrSplit(report, '\n', absl::SkipWhitespace());
      return absl::FailedPreconditionError(
          absl::StrCat("camera \"", config_.id(), "\": the controller's settings differ from the node's (",
                       absl::StrJoin(lines, "; "), "); restart the node with the controller's rig"));
    }
  }
  TakePlan plan;
  plan.path = absl::StrCat(request.take_dir(), "/cameras/", config_.id(), ".h5");
  plan.info.camera_id = config_.id();
  plan.info.take_id = request.take_id();
  plan.info.pixel_format = PixelFormatName(config_.pixel_format());
  plan.info.exposure_us = config_.exposure_us();
  plan.info.gain_db = config_.gain_db();
  {
    // What each frame's pattern index means, and the camera's calibration, in the file itself.
    nlohmann::json patterns = nlohmann::json::array();
    for (const v1::SchedulePattern& p : request.patterns()) {
      patterns.push_back({{"index", p.index()},
                          {"name", p.name()},
                          {"polarization", p.polarization() == v1::POLARIZATION_PARALLEL ? "parallel" : "cross"}});
    }
    plan.info.patterns_json = patterns.dump();
    v1::CameraConfig calibration;
    *calibration.mutable_intrinsics() = config_.intrinsics();
    *calibration.mutable_pose() = config_.pose();
    google::protobuf::util::JsonPrintOptions o;
    o.preserve_proto_field_names = true;
    (void)google::protobuf::util::MessageToJsonString(calibration, &plan.info.calibration_json, o);
  }
  plan.t0_ns = request.t0_bus_ns();
  plan.slot_ns = base->SlotStartNs(1);
  plan.slot_start_ns = [b = *base](int64_t k) { return b.SlotStartNs(k); };
  plan.slots = request.slot_count();
  plan.divider = std::max<uint32_t>(1, request.trigger_plan().divider());
  plan.phase = request.trigger_plan().slot_phase();
  plan.trigger_delay_ns = request.trigger_delay_ns();
  plan.patterns_per_cycle = std::max<uint32_t>(1, request.patterns_per_cycle());
  plan.burst = request.burst();
  if (request.burst_bytes() > 0) plan.burst_bytes = request.burst_bytes();
  plan.first_frame_id = static_cast<uint64_t>(last_frame_id_.load() + 1);
  plan.started = !request.start_later();
  plan.preview_pattern = request.preview_pattern();
  // The frame size is the device's (the sim renders at a scale of the rig's sensor): the file takes it from the first
  // frame.
  STAGE_ASSIGN_OR_RETURN(auto recorder, TakeRecorder::Start(std::move(plan)));
  recorder_ = std::move(recorder);
  take_id_ = request.take_id();
  const DeviceStats d = device_->Stats();
  link_losses_at_arm_ = d.link_losses;
  link_down_at_arm_ = !d.link_up;
  v1::ArmCameraResponse response;
  response.set_expected_frames(recorder_->expected_frames());
  response.set_path(recorder_->path());
  Logger("camera.node")->info("{}: armed for take {}: {} frames", config_.id(), take_id_, response.expected_frames());
  return response;
}

absl::StatusOr<std::shared_ptr<TakeRecorder>> CameraNode::ArmedRecorder(const std::string& take_id) const {
  std::lock_guard<std::mutex> lock(take_mutex_);
  if (!recorder_ || take_id_ != take_id) {
    return absl::NotFoundError(absl::StrCat("camera \"", config_.id(), "\": take \"", take_id, "\" is not armed here"));
  }
  return recorder_;
}

absl::StatusOr<v1::ArmCameraResponse> CameraNode::UpdateTake(const v1::UpdateTakeRequest& request) {
  STAGE_ASSIGN_OR_RETURN(std::shared_ptr<TakeRecorder> recorder, ArmedRecorder(request.take_id()));
  PlanUpdate update;
  if (request.has_t0_bus_ns()) {
    update.t0_ns = request.t0_bus_ns();
    // The take's first exposure follows the last frame delivered before it starts.
    update.first_frame_id = static_cast<uint64_t>(last_frame_id_.load() + 1);
  }
  update.slots = request.slot_count();
  for (const v1::SlotRange& r : request.paused()) update.paused.emplace_back(r.first(), r.end());
  if (absl::Status s = recorder->Update(update); !s.ok()) {
    return Annotate(s, absl::StrCat("camera \"", config_.id(), "\": take ", request.take_id()));
  }
  v1::ArmCameraResponse response;
  response.set_expected_frames(recorder->expected_frames());
  response.set_path(recorder->path());
  Logger("camera.node")
      ->info("{}: take {} now expects {} frames", config_.id(), request.take_id(), response.expected_frames());
  return response;
}

absl::StatusOr<v1::Preview> CameraNode::GetPreview(const v1::GetPreviewRequest& request) const {
  std::shared_ptr<TakeRecorder> recorder;
  std::string take_id;
  {
    std::lock_guard<std::mutex> lock(take_mutex_);
    recorder = recorder_;
    take_id = take_id_;
  }
  std::optional<PreviewFrame> latest = recorder ? recorder->LatestPreview() : std::nullopt;
  if (!latest) {
    return absl::NotFoundError(absl::StrCat("camera \"", config_.id(), "\": no preview (no take is recording)"));
  }
  STAGE_ASSIGN_OR_RETURN(v1::Preview preview,
                         MakePreview(*latest->frame, request.max_size() ? request.max_size() : 256));
  v1::FrameMetadata* m = preview.mutable_frame();
  m->set_camera_id(config_.id());
  m->set_take_id(take_id);
  m->set_frame_id(latest->frame->frame_id);
  m->set_device_timestamp_ns(latest->frame->device_timestamp_ns);
  m->set_controller_time_ns(latest->controller_time_ns);
  m->set_slot(latest->slot);
  m->set_status(v1::FRAME_STATUS_OK);
  m->set_exposure_us(latest->frame->exposure_us);
  return preview;
}

absl::StatusOr<v1::CameraTakeReport> CameraNode::Finish(const v1::FinishCameraRequest& request) {
  STAGE_ASSIGN_OR_RETURN(std::shared_ptr<TakeRecorder> recorder, ArmedRecorder(request.take_id()));
  // Frames may still be on their way (rendering, in flight): wait while they keep coming, up to drain_ms of silence.
  const auto drain = std::chrono::milliseconds(request.drain_ms() > 0 ? request.drain_ms() : 2000);
  const auto expected = recorder->expected_frames();
  int64_t seen = -1;
  auto quiet_since = std::chrono::steady_clock::now();
  while (true) {
    const int64_t now_seen = recorder->frames_received();
    if (now_seen >= expected) break;
    if (now_seen != seen) {
      seen = now_seen;
      quiet_since = std::chrono::steady_clock::now();
    } else if (std::chrono::steady_clock::now() - quiet_since >= drain) {
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  {
    std::lock_guard<std::mutex> lock(take_mutex_);
    finishing_ = recorder;
    finishing_id_ = take_id_;
    recorder_.reset();  // frames from now on are not the take's
    take_id_.clear();
  }
  struct Finished {
    CameraNode* node;
    ~Finished() {
      std::lock_guard<std::mutex> lock(node->take_mutex_);
      node->finishing_.reset();
      node->finishing_id_.clear();
    }
  } finished{this};
  {
    // An outage no frame came after reaches the end of the take (the link is down, or came back after the take).
    const DeviceStats d = device_->Stats();
    const int64_t outages = static_cast<int64_t>(d.link_losses - link_losses_at_arm_) + (link_down_at_arm_ ? 1 : 0);
    recorder->ReportLinkOutages(std::max<int64_t>(0, outages), d.link_detail);
    // Frames the camera was triggered for and is still producing: exposed, not delivered when the take ended.
    const DeviceBacklog backlog = device_->Backlog();
    recorder->ReportUndelivered(backlog.frames_owed, backlog.activity);
  }
  const TakeRecording rec = recorder->Finish([&](int64_t done, int64_t total) {
    if (done == total || done % 200 == 0) {
      Logger("camera.node")->info("{}: offloading take {}: {}/{} frames", config_.id(), request.take_id(), done, total);
    }
  });
  v1::CameraTakeReport report;
  report.set_camera_id(config_.id());
  report.set_path(recorder->path());
  for (const SlotOutcome& o : rec.slots) {
    v1::SlotRecord* r = report.add_slots();
    r->set_slot(o.slot);
    r->set_pattern(o.pattern);
    r->set_reason(storage::ToProto(o.reason));
    if (o.frame_id) r->set_frame_id(*o.frame_id);
    r->set_detail(o.detail);
  }
  for (const auto& [slot, b] : rec.brightness) {
    report.add_brightness_slots(slot);
    report.add_brightness(b);
  }
  report.set_frames_received(rec.frames_received);
  report.set_frames_written(rec.frames_written);
  const metrics::Labels camera = {{"camera", config_.id()}};
  auto& registry = metrics::Registry::Default();
  registry
      .GetCounter("stage_camera_frames_written_total", "Frames of finished takes written to their frame files", camera)
      ->Increment(static_cast<double>(rec.frames_written));
  registry
      .GetCounter("stage_camera_frames_dropped_total",
                  "Frames of finished takes not written: expected from the camera and lost (the ledger says why)",
                  camera)
      ->Increment(static_cast<double>(std::max<int64_t>(0, expected - rec.frames_written)));
  report.set_frames_unmatched(rec.frames_unmatched);
  report.set_bytes(rec.bytes);
  report.set_max_timing_error_ns(rec.max_timing_error_ns);
  report.set_error(rec.error);
  Logger("camera.node")
      ->info("{}: take {} finished: {} of {} frames written{}", config_.id(), request.take_id(), rec.frames_written,
             expected, rec.error.empty() ? "" : ", " + rec.error);
  return report;
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
            timing::TriggerSchedulerOptions{
                .max_late_ns = header.max_late_ns() > 0 ? header.max_late_ns() : 100'000,
                .keep_all_leads = header.report_leads(),
                .realtime_priority = static_cast<int>(header.realtime_priority()),
                .fire_lateness = metrics::Registry::Default().GetHistogram(
                    "stage_camera_trigger_lateness_seconds",
                    "How late scheduled software triggers fired after their time",
                    metrics::ExponentialBounds(1e-6, 2, 15), {{"camera", node->config_.id()}})},
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
    for (const auto& [outcome, n] : {std::pair{"fired", stats.fired}, {"late", stats.late}, {"missed", stats.missed}}) {
      metrics::Registry::Default()
          .GetCounter("stage_camera_triggers_total",
                      "Scheduled software triggers by outcome: fired, late (not fired: past the late slack), missed "
                      "(arrived too late, or the stream stopped first)",
                      {{"camera", id}, {"outcome", outcome}})
          ->Increment(static_cast<double>(n));
    }
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
