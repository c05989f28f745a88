// gRPC StageController service.
#include "controller_service.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "event_writer.h"
#include "stage/common/clock.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"
#include "stage/timing/schedule.h"
#include "stage/timing/timing_tool.h"
#include "stage/timing/verifier.h"
#include "stage/v1/processing_worker.grpc.pb.h"
#include "trigger_streamer.h"

namespace stage::controller {

v1::ClockMapping ClockMappingOf(const v1::ClockStatus& clock) {
  v1::ClockMapping m;
  m.set_offset_ns(clock.offset_ns());
  m.set_drift_ppm(clock.drift_known() ? clock.drift_ppm() : 0.0);
  m.set_at_unix_ns(clock.estimate_at_unix_ns());
  return m;
}

std::vector<NodeTarget> TargetsFromRig(const v1::RigConfig& rig, const v1::Schedule* schedule) {
  std::vector<NodeTarget> targets;
  int64_t quarter_slot_ns = 0;
  if (schedule != nullptr && schedule->time_base().ticks_per_ns() > 0) {
    quarter_slot_ns = schedule->time_base().ticks_per_slot() / schedule->time_base().ticks_per_ns() / 4;
  }
  for (const auto& c : rig.cameras()) {
    NodeTarget t{c.id(), v1::NODE_KIND_CAMERA, c.role(), c.address()};
    const v1::CameraTiming* timing = schedule != nullptr ? timing::FindCameraTiming(*schedule, c.id()) : nullptr;
    if (timing != nullptr && c.trigger().source() == v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE) {
      const int64_t slack_ns = timing->late_slack_ticks() / schedule->time_base().ticks_per_ns();
      t.clock_limit_ns = std::max<int64_t>(10'000, slack_ns / 2);
      t.clock_required = true;
      t.clock_limit_reason =
          fmt::format("scheduled software triggers: a clock error moves the exposure; half its late slack of {:.1f} us",
                      slack_ns / 1e3);
    } else if (quarter_slot_ns > 0) {
      t.clock_limit_ns = quarter_slot_ns;
      t.clock_limit_reason = "frames are matched to slots by timestamp: a quarter slot";
    }
    targets.push_back(std::move(t));
  }
  for (const auto& n : rig.light_nodes()) {
    NodeTarget t{n.id(), v1::NODE_KIND_LIGHT, v1::CAMERA_ROLE_UNSPECIFIED, n.address()};
    if (quarter_slot_ns > 0) {
      t.clock_limit_ns = quarter_slot_ns;
      t.clock_limit_reason = "measured slot edges are compared with the schedule: a quarter slot";
    }
    targets.push_back(std::move(t));
  }
  for (const auto& w : rig.processing_workers()) {
    targets.push_back({w.id(), v1::NODE_KIND_PROCESSING_WORKER, v1::CAMERA_ROLE_UNSPECIFIED, w.address()});
  }
  return targets;
}

ControllerService::ControllerService(LoadedRig rig, HealthMonitor* monitor)
    : rig_(std::move(rig)),
      stage_id_(rig_.rig.stage().id()),
      stage_name_(rig_.rig.stage().name()),
      rig_hash_(RigHash(rig_.rig)),
      monitor_(monitor),
      estop_(std::make_unique<controller::EmergencyStop>(rig_.rig)) {
  auto log = Logger("controller.timing");
  auto report = timing::CheckTiming(rig_, {});
  if (!report.ok()) {
    log->error("the rig's schedule cannot be compiled: {}", report.status().message());
    return;
  }
  timing_ = *std::move(report);
  for (const v1::Violation& v : timing_.violations()) {
    const std::string line = fmt::format("{} {}{}: {} (fix: {})", v.check(), v.device(),
                                         v.slot() >= 0 ? fmt::format(" slot {}", v.slot()) : "", v.message(), v.fix());
    if (v.severity() == v1::SEVERITY_ERROR) {
      log->error("{}", line);
    } else {
      log->warn("{}", line);
    }
  }
  log->info("schedule {}: {} patterns at {} slots/s, {} error(s), {} warning(s)", timing_.schedule().hash(),
            timing_.schedule().patterns_size(), timing_.schedule().time_base().slot_rate_hz(), timing_.errors(),
            timing_.warnings());
}

v1::StageStatus ControllerService::Status() const {
  v1::StageStatus status;
  status.set_stage_id(stage_id_);
  status.set_stage_name(stage_name_);
  status.set_time_unix_ns(UnixNowNs());
  int up = 0;
  for (v1::NodeStatus& node : monitor_->Snapshot()) {
    if (node.state() == v1::NODE_STATE_UP) ++up;
    *status.add_nodes() = std::move(node);
  }
  status.set_nodes_up(up);
  status.set_nodes_total(status.nodes_size());
  status.set_session_state(capturer_ ? capturer_->state() : v1::SESSION_STATE_IDLE);
  if (capturer_) status.set_current_take_id(capturer_->current_take_id());
  *status.mutable_controller() =
      MakeNodeInfo(stage_id_, v1::NODE_KIND_CONTROLLER, v1::CAMERA_ROLE_UNSPECIFIED, "", rig_hash_);
  status.set_schedule_hash(timing_.schedule().hash());
  status.set_timing_errors(timing_.errors());
  status.set_timing_warnings(timing_.warnings());
  std::string why;
  status.set_estop_latched(estop_->latched(&why));
  status.set_estop_reason(why);
  if (devices_ != nullptr) {
    for (v1::NodeDevice& d : devices_->Snapshot()) *status.add_devices() = std::move(d);
  }
  return status;
}

grpc::Status ControllerService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = MakeNodeInfo(stage_id_, v1::NODE_KIND_CONTROLLER, v1::CAMERA_ROLE_UNSPECIFIED, "", rig_hash_);
  return grpc::Status::OK;
}

grpc::Status ControllerService::GetStageStatus(grpc::ServerContext*, const v1::GetStageStatusRequest*,
                                               v1::StageStatus* response) {
  *response = Status();
  return grpc::Status::OK;
}

grpc::Status ControllerService::WatchStageStatus(grpc::ServerContext* context,
                                                 const v1::WatchStageStatusRequest* request,
                                                 grpc::ServerWriter<v1::StageStatus>* writer) {
  auto heartbeat =
      std::chrono::milliseconds(request->heartbeat_ms() == 0 ? 1000 : std::max(50u, request->heartbeat_ms()));
  // Wake at least this often to notice a cancelled call or a shutting-down server.
  auto tick = std::min<std::chrono::milliseconds>(heartbeat, std::chrono::milliseconds(200));
  uint64_t seen = monitor_->generation();
  auto last_sent = std::chrono::steady_clock::now();
  if (!writer->Write(Status())) return grpc::Status::OK;
  while (!context->IsCancelled()) {
    uint64_t now_gen = monitor_->WaitForChange(seen, tick);
    auto now = std::chrono::steady_clock::now();
    if (now_gen == seen && now - last_sent < heartbeat) continue;
    seen = now_gen;
    last_sent = now;
    if (!writer->Write(Status())) break;  // the client went away
  }
  return grpc::Status::OK;
}

grpc::Status ControllerService::CheckTiming(grpc::ServerContext*, const v1::TimingQuery* request,
                                            v1::TimingReport* response) {
  auto report = timing::CheckTiming(rig_, *request);
  if (!report.ok()) return ToGrpcStatus(report.status());
  *response = *std::move(report);
  return grpc::Status::OK;
}

grpc::Status ControllerService::RehearseTriggers(grpc::ServerContext* context,
                                                 const v1::RehearseTriggersRequest* request,
                                                 v1::TriggerRehearsal* response) {
  if (timing_.schedule().hash().empty()) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "the rig's schedule could not be compiled");
  }
  if (timing_.errors() > 0) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("the rig's schedule has ", timing_.errors(),
                                     " timing error(s); nothing is triggered until they are fixed (stagectl timing "
                                     "check)"));
  }
  const int64_t slots =
      request->slot_count() > 0 ? request->slot_count() : timing_.schedule().time_base().slot_rate_hz();
  if (slots > 100 * static_cast<int64_t>(timing_.schedule().time_base().slot_rate_hz())) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("a rehearsal of ", slots, " slots is longer than 100 s; ask for fewer"));
  }
  // The clock measurement of every node, for the conversion to its clock.
  std::map<std::string, v1::ClockStatus> clocks;
  for (const v1::NodeStatus& n : monitor_->Snapshot()) clocks[n.id()] = n.clock();
  std::vector<TriggerTarget> targets;
  for (const v1::CameraConfig& c : rig_.rig.cameras()) {
    if (c.trigger().source() != v1::TRIGGER_SOURCE_SCHEDULED_SOFTWARE) continue;
    TriggerTarget t;
    t.id = c.id();
    t.address = c.address();
    t.timing = *timing::FindCameraTiming(timing_.schedule(), c.id());
    if (clocks[c.id()].measured()) t.clock = ClockMappingOf(clocks[c.id()]);
    targets.push_back(std::move(t));
  }
  if (targets.empty()) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "no camera of the rig uses trigger.source scheduled-software: there is nothing to rehearse");
  }
  const v1::Schedule& schedule = timing_.schedule();
  TriggerStreamOptions options;
  options.take_id = "rehearsal";
  options.slot_rate_hz = schedule.time_base().slot_rate_hz();
  options.t0_unix_ns =
      UnixNowNs() + static_cast<int64_t>(request->start_in_ms() > 0 ? request->start_in_ms() : 500) * 1'000'000;
  options.slot_count = slots;
  options.lead_ns =
      schedule.trigger_lead_slots() * schedule.time_base().ticks_per_slot() / schedule.time_base().ticks_per_ns();
  options.realtime_priority = rig_.rig.timing().trigger_realtime_priority();
  // The nodes convert with the latest measurement of their clocks, also during the rehearsal.
  options.clock_source = [this](const std::string& id) -> std::optional<v1::ClockMapping> {
    for (const v1::NodeStatus& n : monitor_->Snapshot()) {
      if (n.id() == id && n.clock().measured()) return ClockMappingOf(n.clock());
    }
    return std::nullopt;
  };
  auto log = Logger("controller.timing");
  log->info("trigger rehearsal: {} slots to {} camera(s), {} slots ahead", slots, targets.size(),
            schedule.trigger_lead_slots());
  TriggerStreamer streamer(options, targets);
  streamer.Start();
  // A client that gives up (stagectl's deadline, Ctrl-C) ends the rehearsal.
  std::atomic<bool> done{false};
  std::thread watcher([&] {
    while (!done.load()) {
      if (context->IsCancelled()) {
        streamer.Cancel();
        return;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  });
  std::vector<absl::StatusOr<v1::TriggerReport>> results = streamer.Wait();
  done.store(true);
  watcher.join();
  if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "the rehearsal was cancelled");
  response->set_slot_count(slots);
  response->set_lead_ns(options.lead_ns);
  for (size_t i = 0; i < targets.size(); ++i) {
    v1::CameraRehearsal* c = response->add_cameras();
    c->set_camera_id(targets[i].id);
    *c->mutable_clock() = targets[i].clock;
    if (results[i].ok()) {
      *c->mutable_report() = *results[i];
    } else {
      c->set_error(std::string(results[i].status().message()));
    }
  }
  return grpc::Status::OK;
}

grpc::Status ControllerService::ExportTiming(grpc::ServerContext*, const v1::TimingExportRequest* request,
                                             v1::TimingExport* response) {
  auto out = timing::ExportTiming(rig_, *request);
  if (!out.ok()) return ToGrpcStatus(out.status());
  *response = *std::move(out);
  return grpc::Status::OK;
}

absl::Status ControllerService::EnableCapture(CaptureOptions options, CaptureDevices devices) {
  // The session's state is part of the stage's status: its changes wake the status watchers too.
  options.on_state_change = [monitor = monitor_] { monitor->NotifyChange(); };
  options.estop = estop_.get();
  STAGE_ASSIGN_OR_RETURN(
      capturer_, Capturer::Create(rig_, timing_.schedule(), timing_.errors(), std::move(options), std::move(devices)));
  return absl::OkStatus();
}

grpc::Status ControllerService::Capture(grpc::ServerContext* context, const v1::CaptureRequest* request,
                                        grpc::ServerWriter<v1::CaptureEvent>* writer) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  EventWriter events(context, writer);
  auto summary = capturer_->Capture(*request, [&events](const v1::CaptureEvent& e) { events.Push(e); });
  events.Finish();
  if (!summary.ok()) return ToGrpcStatus(summary.status());
  return grpc::Status::OK;
}

grpc::Status ControllerService::WatchTake(grpc::ServerContext* context, const v1::WatchTakeRequest* request,
                                          grpc::ServerWriter<v1::CaptureEvent>* writer) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  // The take's events come on its threads; EventWriter writes them on its own, so that a slow follower never holds the
  // take up. Following ends with the take's summary, or the session's idle or error state (a take that ended without
  // one), or an event of another take.
  EventWriter events(context, writer);
  std::mutex mutex;
  std::condition_variable wake;
  bool ended = false;                   // guarded by mutex
  std::string following;                // guarded by mutex; empty until Follow has answered
  bool live = false;                    // guarded by mutex: where the take stood is queued; events go straight on
  std::vector<v1::CaptureEvent> early;  // guarded by mutex: events that came before that
  auto followed = capturer_->Follow(request->take_id(), [&](const v1::CaptureEvent& e) {
    std::lock_guard<std::mutex> lock(mutex);
    if (!following.empty() && e.take_id() != following) {
      ended = true;
    } else {
      if (live) {
        events.Push(e);
      } else {
        early.push_back(e);
      }
      ended = ended || e.has_summary() ||
              (e.has_state() && (e.state() == v1::SESSION_STATE_IDLE || e.state() == v1::SESSION_STATE_ERROR));
    }
    if (ended) wake.notify_all();
  });
  if (!followed.ok()) {
    events.Finish();
    if (request->take_id().empty()) return ToGrpcStatus(followed.status());
    // A take that has ended: its summary is all there is to follow.
    auto take = capturer_->GetTake(request->take_id());
    if (!take.ok()) return ToGrpcStatus(take.status());
    v1::CaptureEvent e;
    e.set_take_id(take->take_id());
    *e.mutable_summary() = *std::move(take);
    writer->Write(e);
    return grpc::Status::OK;
  }
  {
    // Where the take stands (as it was when the subscription began), then what came since, then what comes.
    std::unique_lock<std::mutex> lock(mutex);
    following = followed->take_id;
    for (const auto* e : {&followed->state, &followed->progress, &followed->summary}) {
      if (e->has_value()) events.Push(**e);
    }
    for (const v1::CaptureEvent& e : early) events.Push(e);
    live = true;
    ended = ended || followed->summary.has_value();
    while (!ended && !context->IsCancelled()) wake.wait_for(lock, std::chrono::milliseconds(200));
  }
  capturer_->Unfollow(followed->id);
  events.Finish();
  return grpc::Status::OK;
}

grpc::Status ControllerService::GetLedger(grpc::ServerContext*, const v1::GetLedgerRequest* request,
                                          v1::LedgerPage* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  auto page = capturer_->GetLedger(*request);
  if (!page.ok()) return ToGrpcStatus(page.status());
  *response = *std::move(page);
  return grpc::Status::OK;
}

grpc::Status ControllerService::Arm(grpc::ServerContext* context, const v1::CaptureRequest* request,
                                    grpc::ServerWriter<v1::CaptureEvent>* writer) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  EventWriter events(context, writer);
  auto summary = capturer_->Arm(*request, [&events](const v1::CaptureEvent& e) { events.Push(e); });
  if (summary.ok()) {
    v1::CaptureEvent last;
    last.set_take_id(summary->take_id());
    *last.mutable_summary() = *summary;
    events.Push(last);
  }
  events.Finish();
  if (!summary.ok()) return ToGrpcStatus(summary.status());
  return grpc::Status::OK;
}

namespace {
grpc::Status Reply(const absl::StatusOr<v1::SessionReply>& r, v1::SessionReply* response) {
  if (!r.ok()) return ToGrpcStatus(r.status());
  *response = *r;
  return grpc::Status::OK;
}
}  // namespace

grpc::Status ControllerService::Pause(grpc::ServerContext*, const v1::SessionRequest*, v1::SessionReply* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  return Reply(capturer_->Pause(), response);
}

grpc::Status ControllerService::Resume(grpc::ServerContext*, const v1::SessionRequest*, v1::SessionReply* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  return Reply(capturer_->Resume(), response);
}

grpc::Status ControllerService::Abort(grpc::ServerContext*, const v1::SessionRequest*, v1::SessionReply* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  return Reply(capturer_->Abort(), response);
}

grpc::Status ControllerService::EmergencyStop(grpc::ServerContext*, const v1::EmergencyStopRequest* request,
                                              v1::EmergencyStopReply* response) {
  *response = estop_->Stop(request->reason());
  monitor_->NotifyChange();
  // The lights are dark and the operator hears so now; the take in progress, if any, is aborted after the answer
  // (aborting finishes every camera, which takes a while). Its records are kept.
  std::lock_guard<std::mutex> lock(estop_abort_mutex_);
  if (estop_abort_.joinable()) estop_abort_.join();
  estop_abort_ = std::thread([this] {
    if (!capturer_) return;
    const v1::SessionState state = capturer_->state();
    if (state == v1::SESSION_STATE_ARMED || state == v1::SESSION_STATE_CAPTURING || state == v1::SESSION_STATE_PAUSED) {
      if (auto aborted = capturer_->Abort(); !aborted.ok()) {
        Logger("controller")->warn("emergency stop: the take could not be aborted: {}", aborted.status().message());
      }
    }
  });
  return grpc::Status::OK;
}

ControllerService::~ControllerService() {
  std::lock_guard<std::mutex> lock(estop_abort_mutex_);
  if (estop_abort_.joinable()) estop_abort_.join();
}

grpc::Status ControllerService::ResetEmergencyStop(grpc::ServerContext*, const v1::ResetEmergencyStopRequest*,
                                                   v1::EmergencyStopReply* response) {
  auto reply = estop_->Reset();
  monitor_->NotifyChange();
  if (!reply.ok()) return ToGrpcStatus(reply.status());
  *response = *std::move(reply);
  return grpc::Status::OK;
}

grpc::Status ControllerService::GetPreview(grpc::ServerContext*, const v1::ControllerPreviewRequest* request,
                                           v1::Preview* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  auto preview = capturer_->GetPreview(request->camera_id());
  if (!preview.ok()) return ToGrpcStatus(preview.status());
  *response = std::move(*preview);
  return grpc::Status::OK;
}

grpc::Status ControllerService::ListTakes(grpc::ServerContext*, const v1::ListTakesRequest*, v1::TakeList* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  auto list = capturer_->ListTakes();
  if (!list.ok()) return ToGrpcStatus(list.status());
  *response = std::move(*list);
  return grpc::Status::OK;
}

grpc::Status ControllerService::GetTake(grpc::ServerContext*, const v1::GetTakeRequest* request,
                                        v1::TakeSummary* response) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  auto take = capturer_->GetTake(request->take_id());
  if (!take.ok()) return ToGrpcStatus(take.status());
  *response = std::move(*take);
  return grpc::Status::OK;
}

grpc::Status ControllerService::ProcessTake(grpc::ServerContext* context, const v1::ProcessTakeRequest* request,
                                            grpc::ServerWriter<v1::ProcessingProgress>* writer) {
  if (!capturer_) return ToGrpcStatus(absl::FailedPreconditionError("this controller records no takes"));
  auto take = capturer_->GetTake(request->take_id());
  if (!take.ok()) return ToGrpcStatus(take.status());
  // The worker: the one asked for, or the first that is up.
  const v1::NodeStatus* worker = nullptr;
  const std::vector<v1::NodeStatus> nodes = monitor_->Snapshot();
  std::vector<std::string> known;
  for (const v1::NodeStatus& n : nodes) {
    if (n.kind() != v1::NODE_KIND_PROCESSING_WORKER) continue;
    known.push_back(n.id());
    if (!request->worker_id().empty() ? n.id() == request->worker_id()
                                      : n.state() == v1::NODE_STATE_UP && worker == nullptr) {
      worker = &n;
    }
  }
  if (worker == nullptr) {
    if (!request->worker_id().empty()) {
      return ToGrpcStatus(absl::NotFoundError(absl::StrCat("no processing worker \"", request->worker_id(),
                                                           "\" (the rig has: ", absl::StrJoin(known, ", "), ")")));
    }
    return ToGrpcStatus(absl::UnavailableError(
        known.empty() ? "the rig has no processing worker"
                      : absl::StrCat("no processing worker is up (", absl::StrJoin(known, ", "), ")")));
  }
  v1::ProcessingJob job;
  job.set_stage(request->stage() == v1::PROCESSING_STAGE_UNSPECIFIED ? v1::PROCESSING_STAGE_PHOTOMETRIC
                                                                     : request->stage());
  job.set_take_dir(take->dir());
  job.set_first_frame(request->first_frame());
  job.set_last_frame(request->last_frame());
  *job.mutable_cameras() = request->cameras();
  job.set_geometry_source(request->geometry_source());
  job.set_geometry(request->geometry());
  job.set_calibration(request->calibration());
  job.set_texture_size(request->texture_size());
  job.set_stabilize_method(request->stabilize_method());
  if (request->has_asset()) *job.mutable_asset() = request->asset();  // infer and the other stages refuse one
  if (request->has_graph()) *job.mutable_graph() = request->graph();  // the single stages refuse one
  Logger("controller")
      ->info("take {}: {} on worker {} ({})", request->take_id(), v1::ProcessingStage_Name(job.stage()), worker->id(),
             worker->address());
  auto stub = v1::ProcessingWorker::NewStub(MakeChannel(worker->address()));
  grpc::ClientContext client;
  // The operator's cancel (Ctrl-C on stagectl) reaches the worker.
  std::atomic<bool> done{false};
  std::thread watch([&] {
    while (!done.load()) {
      if (context->IsCancelled()) {
        client.TryCancel();
        return;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  });
  auto reader = stub->Process(&client, job);
  v1::ProcessingProgress progress;
  while (reader->Read(&progress)) {
    if (progress.finished()) progress.set_message(absl::StrCat("take ", take->take_id(), ": ", progress.message()));
    writer->Write(progress);
  }
  grpc::Status status = reader->Finish();
  done = true;
  watch.join();
  if (!status.ok()) {
    // The worker names itself in its own errors; one that did not come from it (unreachable) is named here.
    const std::string name = absl::StrCat("worker \"", worker->id(), "\": ");
    return grpc::Status(status.error_code(), absl::StartsWith(status.error_message(), name)
                                                 ? status.error_message()
                                                 : absl::StrCat(name, status.error_message()));
  }
  return grpc::Status::OK;
}

}  // namespace stage::controller
