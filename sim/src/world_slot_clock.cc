// A generator light node's clock line as the world's bus: see world_slot_clock.h.
#include "stage/sim/world_slot_clock.h"

#include "absl/strings/str_cat.h"
#include "stage/common/status.h"
#include "stage/sim/world_bus.h"

namespace stage::sim {
namespace {

v1::SlotClockRun FromReply(const v1::WorldRunReply& r) {
  v1::SlotClockRun run;
  run.set_first_slot(r.first_slot());
  run.set_end_slot(r.end_slot());
  run.set_first_edge_ns(r.first_edge_ns());
  run.set_current_slot(r.current_slot());
  return run;
}

class WorldSlotClock final : public light::SlotClockGenerator {
 public:
  WorldSlotClock(const std::string& address, const std::string& node_id) : bus_(address, node_id) {}

  std::string Describe() const override { return absl::StrCat("the simulated world's bus at ", bus_.address()); }

  absl::StatusOr<v1::SlotClockRun> Run(const v1::SlotClockRunRequest& request) override {
    v1::RunWorldRequest run;
    run.set_slots(request.slots());
    run.set_lead_slots(request.lead_slots());
    run.set_align_slots(request.align_slots());
    run.set_min_first_slot(request.min_first_slot());
    run.set_plan_only(request.plan_only());
    run.set_first_slot(request.first_slot());
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply reply,
                           bus_.Run(run, std::chrono::steady_clock::now() + std::chrono::seconds(30)));
    return FromReply(reply);
  }

  absl::StatusOr<v1::SlotClockRun> End(int64_t align_slots) override {
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply reply, bus_.End(align_slots));
    return FromReply(reply);
  }

  absl::StatusOr<v1::SlotClockRun> Get() override {
    STAGE_ASSIGN_OR_RETURN(const v1::WorldRunReply reply, bus_.Get());
    return FromReply(reply);
  }

 private:
  WorldBus bus_;
};

}  // namespace

std::unique_ptr<light::SlotClockGenerator> NewWorldSlotClock(const std::string& world_address,
                                                             const std::string& node_id) {
  return std::make_unique<WorldSlotClock>(world_address, node_id);
}

}  // namespace stage::sim
