// gRPC LightNode service: translates messages to LightNode calls, nothing more.
#pragma once

#include "light_node.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage::light {

class LightService final : public v1::LightNode::Service {
 public:
  explicit LightService(LightNode* node) : node_(node) {}
  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) override;
  grpc::Status GetStats(grpc::ServerContext*, const v1::GetLightStatsRequest*, v1::LightStats* response) override;
  grpc::Status Arm(grpc::ServerContext*, const v1::ArmLightRequest* request, v1::LightStats* response) override;
  grpc::Status Disarm(grpc::ServerContext*, const v1::DisarmLightRequest* request, v1::LightStats* response) override;
  grpc::Status Blackout(grpc::ServerContext*, const v1::BlackoutRequest* request, v1::LightStats* response) override;
  grpc::Status ResetBlackout(grpc::ServerContext*, const v1::ResetBlackoutRequest*, v1::LightStats* response) override;
  grpc::Status Heartbeat(grpc::ServerContext*, const v1::HeartbeatRequest* request, v1::LightStats* response) override;
  grpc::Status RunSlotClock(grpc::ServerContext*, const v1::SlotClockRunRequest* request,
                            v1::SlotClockRun* response) override;
  grpc::Status EndSlotClock(grpc::ServerContext*, const v1::EndSlotClockRequest* request,
                            v1::SlotClockRun* response) override;
  grpc::Status GetSlotClock(grpc::ServerContext*, const v1::GetSlotClockRequest*, v1::SlotClockRun* response) override;
  grpc::Status StartTable(grpc::ServerContext*, const v1::StartTableRequest* request,
                          v1::LightStats* response) override;
  grpc::Status GetClockInput(grpc::ServerContext*, const v1::GetClockInputRequest*, v1::ClockInput* response) override;

 private:
  LightNode* node_;
};

}  // namespace stage::light
