#include "stage_link.h"

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "stage/common/clock.h"
#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/proto_json.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/controller.grpc.pb.h"

namespace stage::console {
namespace {

Reply Json(const google::protobuf::Message& m) { return {"application/json", ToContractJson(m)}; }

}  // namespace

absl::Status StageLinkOptions::Validate() const {
  if (controller.empty()) return absl::InvalidArgumentError("--controller: the controller's address is needed");
  if (call_timeout_ms < 100) return absl::InvalidArgumentError("call timeout must be at least 100 ms");
  if (retry_ms < 10) return absl::InvalidArgumentError("retry interval must be at least 10 ms");
  if (!(alarms.thermal_load > 0)) return absl::InvalidArgumentError("the thermal alarm threshold must be positive");
  return absl::OkStatus();
}

struct StageLink::Impl {
  std::unique_ptr<v1::StageController::Stub> stub;
  mutable std::mutex mutex;
  std::condition_variable wake;
  std::string latest_status = "{}";                  // guarded by mutex
  std::shared_ptr<grpc::ClientContext> status_call;  // guarded by mutex: cancelled by Stop
  std::shared_ptr<grpc::ClientContext> take_call;    // guarded by mutex
  std::string followed_take;                         // guarded by mutex
  std::thread take_thread;                           // guarded by mutex
  // The take streams arm and capture started (each as long as its take): cancelled by Stop (the take runs on),
  // reaped once finished.
  struct CommandCall {
    std::thread thread;
    std::shared_ptr<grpc::ClientContext> context;
    std::shared_ptr<std::atomic<bool>> finished;
  };
  std::vector<CommandCall> command_calls;  // guarded by mutex
};

StageLink::StageLink(StageLinkOptions options, EventLog* events, AlarmBook* alarms)
    : options_(std::move(options)), events_(events), alarms_(alarms), impl_(std::make_unique<Impl>()) {
  impl_->stub = v1::StageController::NewStub(MakeChannel(options_.controller));
}

StageLink::~StageLink() { Stop(); }

void StageLink::Start() {
  status_thread_ = std::thread([this] { FollowStatus(); });
}

void StageLink::Stop() {
  if (stopping_.exchange(true)) return;
  std::vector<std::thread> threads;
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    if (impl_->status_call) impl_->status_call->TryCancel();
    if (impl_->take_call) impl_->take_call->TryCancel();
    impl_->wake.notify_all();
    for (Impl::CommandCall& c : impl_->command_calls) {
      c.context->TryCancel();
      threads.push_back(std::move(c.thread));
    }
    impl_->command_calls.clear();
    if (impl_->take_thread.joinable()) threads.push_back(std::move(impl_->take_thread));
  }
  if (status_thread_.joinable()) status_thread_.join();
  for (auto& t : threads) {
    if (t.joinable()) t.join();
  }
}

std::string StageLink::LatestStatusJson() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->latest_status;
}

void StageLink::FollowStatus() {
  auto log = Logger("console.link");
  std::string last_error;
  while (!stopping_) {
    auto context = std::make_shared<grpc::ClientContext>();
    {
      std::lock_guard<std::mutex> lock(impl_->mutex);
      if (stopping_) return;
      impl_->status_call = context;
    }
    v1::WatchStageStatusRequest request;
    request.set_heartbeat_ms(1000);
    auto reader = impl_->stub->WatchStageStatus(context.get(), request);
    v1::StageStatus status;
    while (reader->Read(&status)) {
      if (!connected_.exchange(true)) {
        log->info("following the stage at {}", options_.controller);
        events_->Publish("link", nlohmann::json{{"connected", true}, {"controller", options_.controller}}.dump());
        last_error.clear();
      }
      std::string json = ToContractJson(status);
      {
        std::lock_guard<std::mutex> lock(impl_->mutex);
        impl_->latest_status = json;
      }
      events_->Publish("status", std::move(json));
      auto changed = alarms_->Update(ConditionsOf(status, options_.alarms), UnixNowNs());
      if (!changed.ok()) {
        log->error("alarms: {}", changed.status().message());
      } else {
        for (const Alarm& a : *changed) events_->Publish("alarm", a.ToJson());
      }
      if (!status.current_take_id().empty()) FollowTake(status.current_take_id());
    }
    const grpc::Status end = reader->Finish();
    if (stopping_) return;
    const std::string why = absl::StrCat(options_.controller, ": ", end.error_message());
    if (connected_.exchange(false) || why != last_error) {
      log->warn("the controller does not answer ({}); trying again every {} ms", why, options_.retry_ms);
      events_->Publish(
          "link",
          nlohmann::json{{"connected", false}, {"controller", options_.controller}, {"error", end.error_message()}}
              .dump());
      last_error = why;
    }
    std::unique_lock<std::mutex> lock(impl_->mutex);
    impl_->wake.wait_for(lock, std::chrono::milliseconds(options_.retry_ms), [&] { return stopping_.load(); });
  }
}

void StageLink::FollowTake(const std::string& take_id) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  if (impl_->followed_take == take_id || stopping_) return;
  if (impl_->take_call) impl_->take_call->TryCancel();
  if (impl_->take_thread.joinable()) impl_->take_thread.join();
  impl_->followed_take = take_id;
  auto context = std::make_shared<grpc::ClientContext>();
  impl_->take_call = context;
  impl_->take_thread = std::thread([this, context, take_id] {
    v1::WatchTakeRequest request;
    request.set_take_id(take_id);
    auto reader = impl_->stub->WatchTake(context.get(), request);
    v1::CaptureEvent event;
    while (reader->Read(&event)) events_->Publish("take", ToContractJson(event));
    const grpc::Status end = reader->Finish();
    if (!end.ok() && end.error_code() != grpc::StatusCode::CANCELLED) {
      Logger("console.link")->warn("following take {}: {}", take_id, end.error_message());
    }
  });
}

absl::StatusOr<Reply> StageLink::StartTake(bool capture, const std::string& request_json) {
  v1::CaptureRequest request;
  if (auto s = FromContractJson(request_json.empty() ? "{}" : request_json, &request); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("the take request: ", s.message()));
  }
  // The call runs as long as the take; its first event (or its error) is the answer. Its events are not published:
  // the take's follower (WatchTake) publishes them, once.
  struct First {
    std::mutex mutex;
    std::condition_variable ready;
    bool done = false;
    absl::StatusOr<v1::CaptureEvent> event = absl::UnknownError("no answer");
  };
  auto first = std::make_shared<First>();
  auto context = std::make_shared<grpc::ClientContext>();
  auto finished = std::make_shared<std::atomic<bool>>(false);
  std::thread call([this, capture, request, first, context, finished] {
    auto reader = capture ? impl_->stub->Capture(context.get(), request) : impl_->stub->Arm(context.get(), request);
    v1::CaptureEvent e;
    bool answered = false;
    auto answer = [&](absl::StatusOr<v1::CaptureEvent> what) {
      std::lock_guard<std::mutex> lock(first->mutex);
      first->event = std::move(what);
      first->done = true;
      first->ready.notify_all();
      answered = true;
    };
    while (reader->Read(&e)) {
      if (!answered) answer(e);
    }
    const grpc::Status end = reader->Finish();
    if (!answered) {
      answer(end.ok() ? absl::StatusOr<v1::CaptureEvent>(v1::CaptureEvent()) : FromGrpcStatus(end));
    } else if (!end.ok() && end.error_code() != grpc::StatusCode::CANCELLED) {
      events_->Publish("message", nlohmann::json{{"text", end.error_message()}}.dump());
    }
    *finished = true;
  });
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    auto& calls = impl_->command_calls;
    for (auto it = calls.begin(); it != calls.end();) {
      if (!*it->finished) {
        ++it;
        continue;
      }
      it->thread.join();
      it = calls.erase(it);
    }
    calls.push_back({std::move(call), context, finished});
  }
  std::unique_lock<std::mutex> lock(first->mutex);
  if (!first->ready.wait_for(lock, std::chrono::milliseconds(options_.call_timeout_ms), [&] { return first->done; })) {
    return absl::DeadlineExceededError("the controller took the request but has not answered yet; follow the stage");
  }
  if (!first->event.ok()) return first->event.status();
  return Json(*first->event);
}

absl::StatusOr<Reply> StageLink::Arm(const std::string& request_json) { return StartTake(false, request_json); }
absl::StatusOr<Reply> StageLink::Capture(const std::string& request_json) { return StartTake(true, request_json); }

namespace {

// One unary call with the link's deadline; the reply as JSON.
template <typename Request, typename Response>
absl::StatusOr<Reply> Call(v1::StageController::Stub* stub,
                           grpc::Status (v1::StageController::Stub::*method)(grpc::ClientContext*, const Request&,
                                                                             Response*),
                           const Request& request, int timeout_ms) {
  grpc::ClientContext context;
  SetDeadline(&context, std::chrono::milliseconds(timeout_ms));
  Response reply;
  if (auto s = FromGrpcStatus((stub->*method)(&context, request, &reply)); !s.ok()) return s;
  return Json(reply);
}

}  // namespace

absl::StatusOr<Reply> StageLink::Pause() {
  return Call(impl_->stub.get(), &v1::StageController::Stub::Pause, v1::SessionRequest(), options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Resume() {
  return Call(impl_->stub.get(), &v1::StageController::Stub::Resume, v1::SessionRequest(), options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Abort() {
  return Call(impl_->stub.get(), &v1::StageController::Stub::Abort, v1::SessionRequest(), options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::EmergencyStop(const std::string& reason) {
  v1::EmergencyStopRequest request;
  request.set_reason(reason);
  return Call(impl_->stub.get(), &v1::StageController::Stub::EmergencyStop, request, options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::ResetEmergencyStop() {
  return Call(impl_->stub.get(), &v1::StageController::Stub::ResetEmergencyStop, v1::ResetEmergencyStopRequest(),
              options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Preview(const std::string& camera_id) {
  v1::ControllerPreviewRequest request;
  request.set_camera_id(camera_id);
  return Call(impl_->stub.get(), &v1::StageController::Stub::GetPreview, request, options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Takes() {
  return Call(impl_->stub.get(), &v1::StageController::Stub::ListTakes, v1::ListTakesRequest(),
              options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Take(const std::string& take_id) {
  v1::GetTakeRequest request;
  request.set_take_id(take_id);
  return Call(impl_->stub.get(), &v1::StageController::Stub::GetTake, request, options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Ledger(const std::string& take_id, bool lost_only, int page_size,
                                        const std::string& page_token) {
  v1::GetLedgerRequest request;
  request.set_take_id(take_id);
  request.set_lost_only(lost_only);
  request.set_page_size(page_size);
  request.set_page_token(page_token);
  return Call(impl_->stub.get(), &v1::StageController::Stub::GetLedger, request, options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::Timing() {
  return Call(impl_->stub.get(), &v1::StageController::Stub::CheckTiming, v1::TimingQuery(), options_.call_timeout_ms);
}

absl::StatusOr<Reply> StageLink::TimingSvg() {
  grpc::ClientContext context;
  SetDeadline(&context, std::chrono::milliseconds(options_.call_timeout_ms));
  v1::TimingExportRequest request;
  request.set_svg(true);
  v1::TimingExport reply;
  if (auto s = FromGrpcStatus(impl_->stub->ExportTiming(&context, request, &reply)); !s.ok()) return s;
  return Reply{"image/svg+xml", reply.svg()};
}

}  // namespace stage::console
