// The simulated world's bus as a sync generator, and its ground truth: see world_sync_generator.h.
#include "stage/sim/world_sync_generator.h"

#include <grpcpp/grpcpp.h>

#include "absl/strings/str_cat.h"
#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/status.h"
#include "stage/sim/world_bus.h"

namespace stage::sim {
namespace {

using controller::SyncRun;
using controller::SyncRunRequest;

SyncRun FromReply(const v1::WorldRunReply& r) {
  return {r.first_slot(), r.end_slot(), r.first_edge_ns(), r.current_slot()};
}

v1::RunWorldRequest ToRequest(const SyncRunRequest& r) {
  v1::RunWorldRequest w;
  w.set_slots(r.slots);
  w.set_lead_slots(r.lead_slots);
  w.set_align_slots(r.align_slots);
  w.set_min_first_slot(r.min_first_slot);
  return w;
}

class WorldSyncGenerator final : public controller::SyncGenerator {
 public:
  explicit WorldSyncGenerator(const std::string& address) : bus_(address, "controller") {}

  std::string Describe() const override { return absl::StrCat("the simulated world's bus at ", bus_.address()); }

  absl::StatusOr<SyncRun> Plan(const SyncRunRequest& request, std::chrono::steady_clock::time_point give_up) override {
    v1::RunWorldRequest plan = ToRequest(request);
    plan.set_plan_only(true);
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply run, bus_.Run(plan, give_up));
    return FromReply(run);
  }

  absl::StatusOr<SyncRun> Start(const SyncRunRequest& request, const SyncRun& planned,
                                std::chrono::steady_clock::time_point give_up) override {
    v1::RunWorldRequest start = ToRequest(request);
    start.set_first_slot(planned.first_slot);
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply run, bus_.Run(start, give_up));
    return FromReply(run);
  }

  absl::StatusOr<SyncRun> End(int64_t align_slots) override {
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply run, bus_.End(align_slots));
    return FromReply(run);
  }

  absl::StatusOr<SyncRun> GetRun() override {
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply run, bus_.Get());
    return FromReply(run);
  }

 private:
  WorldBus bus_;
};

class WorldTakeTruth final : public controller::TakeTruth {
 public:
  explicit WorldTakeTruth(const std::string& address) : world_(v1::SimWorld::NewStub(MakeChannel(address))) {}

  absl::Status Write(const std::string& dir, int64_t name_offset, int64_t first_frame, int64_t frames,
                     bool scene_only) override {
    v1::GroundTruthRequest gt;
    gt.set_scene_only(scene_only);
    gt.set_dir(dir);
    gt.set_name_offset(name_offset);
    gt.set_first_frame(first_frame);
    gt.set_frames(frames);
    grpc::ClientContext context;
    SetDeadline(&context, std::chrono::minutes(30));
    v1::GroundTruthReply written;
    return FromGrpcStatus(world_->WriteGroundTruth(&context, gt, &written));
  }

 private:
  std::unique_ptr<v1::SimWorld::Stub> world_;
};

}  // namespace

std::unique_ptr<controller::SyncGenerator> NewWorldSyncGenerator(const std::string& world_address) {
  return std::make_unique<WorldSyncGenerator>(world_address);
}

std::unique_ptr<controller::TakeTruth> NewWorldTakeTruth(const std::string& world_address) {
  return std::make_unique<WorldTakeTruth>(world_address);
}

}  // namespace stage::sim
