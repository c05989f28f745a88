// An external sync generator watched through a light node's clock input: see external_sync_generator.h.
#include "external_sync_generator.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <cmath>
#include <mutex>
#include <optional>
#include <thread>

#include "absl/strings/str_cat.h"
#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage::controller {
namespace {

using Clock = std::chrono::steady_clock;

class GrpcClockWitness final : public ClockWitness {
 public:
  explicit GrpcClockWitness(const v1::LightNodeConfig& node)
      : id_(node.id()), address_(node.address()), stub_(v1::LightNode::NewStub(MakeChannel(node.address()))) {}

  std::string Describe() const override { return absl::StrCat("light node ", id_, " at ", address_); }

  absl::StatusOr<v1::ClockInput> Read() override {
    grpc::ClientContext context;
    SetDeadline(&context, std::chrono::seconds(1));
    v1::ClockInput in;
    STAGE_RETURN_IF_ERROR(FromGrpcStatus(stub_->GetClockInput(&context, v1::GetClockInputRequest(), &in)));
    return in;
  }

 private:
  std::string id_, address_;
  std::unique_ptr<v1::LightNode::Stub> stub_;
};

int64_t AlignUp(int64_t slot, int64_t align) {
  align = std::max<int64_t>(1, align);
  const int64_t r = ((slot % align) + align) % align;
  return r == 0 ? slot : slot + (align - r);
}

class ExternalSyncGenerator final : public SyncGenerator {
 public:
  ExternalSyncGenerator(std::unique_ptr<ClockWitness> witness, ExternalGeneratorOptions options)
      : witness_(std::move(witness)), options_(options) {}

  std::string Describe() const override {
    return absl::StrCat("the external generator seen on ", witness_->Describe());
  }
  bool runs_free() const override { return true; }

  absl::StatusOr<SyncRun> Plan(const SyncRunRequest& request, Clock::time_point give_up) override {
    if (request.slots <= 0) return absl::InvalidArgumentError(absl::StrCat("a run of ", request.slots, " slots"));
    STAGE_ASSIGN_OR_RETURN(const v1::ClockInput in, WaitRunning(give_up));
    std::lock_guard<std::mutex> lock(mutex_);
    int64_t first = std::max({in.last_slot() + std::max<int64_t>(1, request.lead_slots), request.min_first_slot,
                              run_ ? run_->end_slot : INT64_MIN});
    first = AlignUp(first, request.align_slots);
    return SyncRun{first, first + request.slots, in.last_edge_ns() + SlotsNs(first - in.last_slot()),
                   in.last_slot()};
  }

  absl::StatusOr<SyncRun> Start(const SyncRunRequest& request, const SyncRun& planned,
                                Clock::time_point give_up) override {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (run_ && run_->first_slot == planned.first_slot) return *run_;  // asked again: it started once
    }
    // The run starts with its first edge: wait for the witness to see it, for as long as the line moves; on a take's
    // first run, until the witness's table has started.
    STAGE_ASSIGN_OR_RETURN(const v1::ClockInput in,
                           WaitForSlot(planned.first_slot, request.first_of_take, give_up));
    SyncRun run = planned;
    if (request.first_of_take) {
      if (in.table_first_slot() != planned.first_slot) {
        // Every light started where the witness did, a slot from the cameras' T0: the take would be out of step.
        return absl::FailedPreconditionError(absl::StrCat(
            "the lights started at slot ", in.table_first_slot(), " of the external clock, not the planned ",
            planned.first_slot, " (seen on ", witness_->Describe(),
            "): T0 was predicted more than half a slot off; is the generator at the rig's rate of ",
            options_.slot_rate_hz, " Hz?"));
      }
      run.first_edge_ns = in.table_first_edge_ns();  // the edge the witness's table started on, as it measured it
    } else {
      // A resume: the lights step on through the gap; the run's first edge from the last one seen, at the rig's rate.
      run.first_edge_ns = in.last_edge_ns() - SlotsNs(in.last_slot() - planned.first_slot);
    }
    run.current_slot = std::min(in.last_slot(), run.end_slot - 1);
    std::lock_guard<std::mutex> lock(mutex_);
    run_ = run;
    return run;
  }

  absl::StatusOr<SyncRun> End(int64_t align_slots) override {
    STAGE_ASSIGN_OR_RETURN(const v1::ClockInput in, witness_->Read());
    std::lock_guard<std::mutex> lock(mutex_);
    if (!run_) return absl::FailedPreconditionError("the external generator has had no run");
    if (in.last_slot() >= run_->end_slot - 1) {
      return absl::FailedPreconditionError(absl::StrCat("the run [", run_->first_slot, ", ", run_->end_slot,
                                                        ") is over (the line is at slot ", in.last_slot(), ")"));
    }
    const int64_t from = std::max(in.last_slot() + options_.end_margin_slots + 1, run_->first_slot);
    run_->end_slot =
        std::min(run_->end_slot, run_->first_slot + AlignUp(from - run_->first_slot, std::max<int64_t>(1, align_slots)));
    run_->current_slot = Current(in, *run_);
    return *run_;
  }

  absl::StatusOr<SyncRun> GetRun() override {
    STAGE_ASSIGN_OR_RETURN(const v1::ClockInput in, witness_->Read());
    std::lock_guard<std::mutex> lock(mutex_);
    if (!run_) return absl::FailedPreconditionError("the external generator has had no run");
    SyncRun run = *run_;
    run.current_slot = Current(in, run);
    // The line went quiet before the run's end: the generator stopped (or its cable came off); its run ended there.
    if (!in.running() && run.current_slot < run.end_slot - 1) run.end_slot = run.current_slot + 1;
    return run;
  }

 private:
  static int64_t Current(const v1::ClockInput& in, const SyncRun& run) {
    return std::clamp<int64_t>(in.last_slot(), run.first_slot - 1, run.end_slot - 1);
  }
  int64_t SlotsNs(int64_t slots) const {
    return static_cast<int64_t>(std::llround(static_cast<double>(slots) * 1e9 / options_.slot_rate_hz));
  }

  absl::StatusOr<v1::ClockInput> WaitRunning(Clock::time_point give_up) {
    while (true) {
      auto in = witness_->Read();
      if (in.ok() && in->running() && in->last_slot() >= 0) return *in;
      if (Clock::now() >= give_up) {
        if (!in.ok()) return Annotate(in.status(), absl::StrCat("the external generator's witness ", witness_->Describe()));
        return absl::FailedPreconditionError(absl::StrCat(
            "the external generator's slot clock is not running on the input of ", witness_->Describe(),
            in->last_slot() < 0 ? " (no edge seen)" : absl::StrCat(" (last edge: slot ", in->last_slot(), ")"),
            ": start the generator, then capture"));
      }
      std::this_thread::sleep_for(options_.poll);
    }
  }

  // Until the witness has seen `slot`'s edge (and, with `table`, started its table); the wait lasts while the line moves
  // (a slow machine), and ends with an error when the line goes quiet first, or stands still until `give_up` (renewed
  // by every edge).
  absl::StatusOr<v1::ClockInput> WaitForSlot(int64_t slot, bool table, Clock::time_point give_up) {
    const auto patience = std::max<Clock::duration>(give_up - Clock::now(), std::chrono::seconds(1));
    int64_t seen = INT64_MIN;
    while (true) {
      auto in = witness_->Read();
      if (in.ok()) {
        if (in->last_slot() >= slot && (!table || in->table_first_slot() >= 0)) return *in;
        if (!in->running() && in->last_slot() >= 0) {
          return absl::UnavailableError(absl::StrCat("the external generator stopped at slot ", in->last_slot(),
                                                     ", before the run's first slot ", slot, " (seen on ",
                                                     witness_->Describe(), ")"));
        }
        if (in->last_slot() > seen) {
          seen = in->last_slot();
          give_up = Clock::now() + patience;
        }
      }
      if (Clock::now() >= give_up) {
        return absl::DeadlineExceededError(absl::StrCat(
            "the run's first slot ", slot, " never came on ", witness_->Describe(),
            in.ok() ? absl::StrCat(" (the line stands at slot ", in->last_slot(), ")")
                    : absl::StrCat(" (", in.status().message(), ")")));
      }
      std::this_thread::sleep_for(options_.poll);
    }
  }

  std::unique_ptr<ClockWitness> witness_;
  ExternalGeneratorOptions options_;
  std::mutex mutex_;
  std::optional<SyncRun> run_;  // guarded by mutex_: the last run started
};

}  // namespace

absl::Status ExternalGeneratorOptions::Validate() const {
  if (!(slot_rate_hz > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("external generator: slot_rate_hz ", slot_rate_hz, " is not above 0"));
  }
  if (end_margin_slots < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("external generator: end_margin_slots ", end_margin_slots, " is below 1"));
  }
  if (poll.count() <= 0) return absl::InvalidArgumentError("external generator: poll is not above 0 ms");
  return absl::OkStatus();
}

std::unique_ptr<ClockWitness> NewGrpcClockWitness(const v1::LightNodeConfig& node) {
  return std::make_unique<GrpcClockWitness>(node);
}

absl::StatusOr<std::unique_ptr<SyncGenerator>> NewExternalSyncGenerator(std::unique_ptr<ClockWitness> witness,
                                                                        ExternalGeneratorOptions options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (witness == nullptr) return absl::InvalidArgumentError("external generator: no clock witness");
  return std::unique_ptr<SyncGenerator>(std::make_unique<ExternalSyncGenerator>(std::move(witness), options));
}

}  // namespace stage::controller
