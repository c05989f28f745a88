// A generator light node as the controller's sync generator: see light_sync_generator.h.
#include "light_sync_generator.h"

#include <grpcpp/grpcpp.h>

#include "absl/strings/str_cat.h"
#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage::controller {
namespace {

SyncRun FromReply(const v1::SlotClockRun& r) {
  return {r.first_slot(), r.end_slot(), r.first_edge_ns(), r.current_slot()};
}

class LightSyncGenerator final : public SyncGenerator {
 public:
  explicit LightSyncGenerator(const v1::LightNodeConfig& node)
      : id_(node.id()), address_(node.address()), stub_(v1::LightNode::NewStub(MakeChannel(node.address()))) {}

  std::string Describe() const override { return absl::StrCat("light node ", id_, " at ", address_); }

  absl::StatusOr<SyncRun> Plan(const SyncRunRequest& request, std::chrono::steady_clock::time_point give_up) override {
    v1::SlotClockRunRequest plan = ToRequest(request);
    plan.set_plan_only(true);
    return Run(plan, give_up);
  }

  absl::StatusOr<SyncRun> Start(const SyncRunRequest& request, const SyncRun& planned,
                                std::chrono::steady_clock::time_point give_up) override {
    v1::SlotClockRunRequest start = ToRequest(request);
    start.set_first_slot(planned.first_slot);
    return Run(start, give_up);
  }

  absl::StatusOr<SyncRun> End(int64_t align_slots) override {
    v1::EndSlotClockRequest end;
    end.set_align_slots(align_slots);
    grpc::ClientContext context;
    SetDeadline(&context, std::chrono::seconds(5));
    v1::SlotClockRun run;
    STAGE_RETURN_IF_ERROR(FromGrpcStatus(stub_->EndSlotClock(&context, end, &run)));
    return FromReply(run);
  }

  absl::StatusOr<SyncRun> GetRun() override {
    grpc::ClientContext context;
    SetDeadline(&context, std::chrono::seconds(1));
    v1::SlotClockRun run;
    STAGE_RETURN_IF_ERROR(FromGrpcStatus(stub_->GetSlotClock(&context, v1::GetSlotClockRequest(), &run)));
    return FromReply(run);
  }

 private:
  static v1::SlotClockRunRequest ToRequest(const SyncRunRequest& r) {
    v1::SlotClockRunRequest out;
    out.set_slots(r.slots);
    out.set_lead_slots(r.lead_slots);
    out.set_align_slots(r.align_slots);
    out.set_min_first_slot(r.min_first_slot);
    out.set_requested_by("controller");
    return out;
  }

  // Planning is a question, and starting the planned run twice starts it once: a node slow to answer is asked again.
  absl::StatusOr<SyncRun> Run(const v1::SlotClockRunRequest& request, std::chrono::steady_clock::time_point give_up) {
    v1::SlotClockRun run;
    STAGE_RETURN_IF_ERROR(Patiently(std::chrono::seconds(5), give_up, [&](grpc::ClientContext* context) {
      return stub_->RunSlotClock(context, request, &run);
    }));
    return FromReply(run);
  }

  std::string id_, address_;
  std::unique_ptr<v1::LightNode::Stub> stub_;
};

}  // namespace

std::unique_ptr<SyncGenerator> NewLightSyncGenerator(const v1::LightNodeConfig& node) {
  return std::make_unique<LightSyncGenerator>(node);
}

}  // namespace stage::controller
