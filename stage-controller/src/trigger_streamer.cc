// Scheduled-trigger streams to camera nodes.
#include "trigger_streamer.h"

#include <grpcpp/grpcpp.h>
#include <sys/prctl.h>

#include <algorithm>
#include <chrono>

#include "absl/strings/str_cat.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"
#include "stage/timing/schedule.h"
#include "stage/timing/slot_clock.h"
#include "stage/v1/camera_node.grpc.pb.h"

namespace stage::controller {

TriggerStreamer::TriggerStreamer(TriggerStreamOptions options, std::vector<TriggerTarget> targets)
    : options_(std::move(options)),
      targets_(std::move(targets)),
      base_(*timing::TimeBase::Create(std::max<uint32_t>(1, options_.slot_rate_hz))) {
  results_.resize(targets_.size(), absl::UnknownError("not run"));
  for (size_t i = 0; i < targets_.size(); ++i) contexts_.push_back(std::make_unique<grpc::ClientContext>());
}

TriggerStreamer::~TriggerStreamer() {
  Cancel();
  Wait();
}

void TriggerStreamer::Start() {
  // No stream outlives its take: the deadline is the last slot's time plus the time to finish.
  const int64_t end_ns = options_.t0_unix_ns + base_.SlotStartNs(options_.first_slot + options_.slot_count) +
                         options_.finish_timeout_ms * 1'000'000;
  for (auto& context : contexts_) {
    context->set_deadline(std::chrono::system_clock::time_point(
        std::chrono::duration_cast<std::chrono::system_clock::duration>(std::chrono::nanoseconds(end_ns))));
  }
  for (size_t i = 0; i < targets_.size(); ++i) threads_.emplace_back([this, i] { Send(i); });
}

std::vector<absl::StatusOr<v1::TriggerReport>> TriggerStreamer::Wait() {
  for (std::thread& t : threads_) {
    if (t.joinable()) t.join();
  }
  return results_;
}

void TriggerStreamer::Cancel() {
  cancelled_.store(true);
  for (auto& context : contexts_) context->TryCancel();
}

void TriggerStreamer::Send(size_t index) {
  prctl(PR_SET_TIMERSLACK, 1UL);
  const TriggerTarget& target = targets_[index];
  const v1::CameraTiming& camera = target.timing;
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  auto channel = MakeChannel(target.address, args);
  auto stub = v1::CameraNode::NewStub(channel);
  v1::TriggerReport report;
  auto writer = stub->StreamTriggers(contexts_[index].get(), &report);

  v1::TriggerStreamMessage header;
  auto* h = header.mutable_header();
  h->set_take_id(options_.take_id);
  h->set_t0_unix_ns(options_.t0_unix_ns);
  *h->mutable_clock() = target.clock;
  h->set_max_late_ns(std::max<int64_t>(0, camera.late_slack_ticks() / base_.ticks_per_ns()));
  h->set_report_leads(options_.report_leads);
  h->set_realtime_priority(options_.realtime_priority);
  if (!writer->Write(header)) {
    results_[index] =
        Annotate(FromGrpcStatus(writer->Finish()), absl::StrCat("camera node ", target.id, " at ", target.address));
    return;
  }

  // Trigger k's time on the controller clock, ns since T0.
  auto time_ns = [&](int64_t k) { return base_.TicksToNs(base_.SlotStartTicks(k) + camera.trigger_ticks()); };
  const int64_t end = options_.first_slot + options_.slot_count;
  const int64_t wake_period = std::max<int64_t>(options_.lead_ns / 4, 1);
  int64_t k = timing::NextFiringSlot(camera, options_.first_slot);
  bool ok = true;
  v1::ClockMapping clock = target.clock;
  int64_t next_clock_update = timing::HostClockNs(/*realtime_clock=*/true) + options_.clock_update_interval_ns;
  while (ok && k < end && !cancelled_.load()) {
    const int64_t now = timing::HostClockNs(/*realtime_clock=*/true);
    if (options_.clock_source && now >= next_clock_update) {
      next_clock_update = now + options_.clock_update_interval_ns;
      std::optional<v1::ClockMapping> latest = options_.clock_source(target.id);
      if (latest && latest->SerializeAsString() != clock.SerializeAsString()) {
        clock = *latest;
        v1::TriggerStreamMessage update;
        *update.mutable_clock() = clock;
        ok = writer->Write(update);
        if (!ok) break;
      }
    }
    v1::TriggerStreamMessage message;
    int64_t sent = 0;
    while (k < end && options_.t0_unix_ns + time_ns(k) - options_.lead_ns <= now) {
      auto* t = message.mutable_batch()->add_triggers();
      t->set_time_ns(time_ns(k));
      t->set_slot(k);
      k += camera.divider();
      ++sent;
    }
    if (sent > 0) ok = writer->Write(message);
    if (!ok || k >= end) break;
    // Sleep until the next trigger must leave, but at least a quarter lead: what falls due meanwhile goes in one
    // message, and every trigger still leaves at least three quarters of the lead ahead of its time.
    const int64_t next_send = options_.t0_unix_ns + time_ns(k) - options_.lead_ns;
    timing::SleepUntilHostNs(std::max(next_send, now + wake_period), /*realtime_clock=*/true);
  }
  writer->WritesDone();
  grpc::Status status = writer->Finish();
  if (!status.ok()) {
    results_[index] = Annotate(FromGrpcStatus(status), absl::StrCat("camera node ", target.id, " at ", target.address));
  } else {
    results_[index] = std::move(report);
  }
}

}  // namespace stage::controller
