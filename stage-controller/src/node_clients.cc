// gRPC clients of the camera and light nodes: see node_clients.h.
#include "node_clients.h"

#include <grpcpp/grpcpp.h>

#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage::controller {
namespace {

class GrpcCameraClient final : public CameraClient {
 public:
  GrpcCameraClient(const std::string& address, std::chrono::milliseconds answer)
      : answer_(answer), stub_(v1::CameraNode::NewStub(MakeChannel(address))) {}

  absl::Status Arm(const v1::ArmCameraRequest& request, SteadyTime give_up, v1::ArmCameraResponse* reply) override {
    return Patiently(answer_, give_up, [&](grpc::ClientContext* c) { return stub_->Arm(c, request, reply); });
  }
  absl::Status UpdateTake(const v1::UpdateTakeRequest& request, SteadyTime give_up) override {
    v1::ArmCameraResponse reply;
    return Patiently(answer_, give_up, [&](grpc::ClientContext* c) { return stub_->UpdateTake(c, request, &reply); });
  }
  absl::Status GetStats(v1::CameraStats* stats) override {
    grpc::ClientContext context;
    SetDeadline(&context, kPoll);
    return FromGrpcStatus(stub_->GetStats(&context, v1::GetStatsRequest(), stats));
  }
  absl::Status GetPreview(const v1::GetPreviewRequest& request, v1::Preview* preview) override {
    grpc::ClientContext context;
    SetDeadline(&context, kPoll);
    return FromGrpcStatus(stub_->GetPreview(&context, request, preview));
  }
  absl::Status Finish(const v1::FinishCameraRequest& request, std::chrono::milliseconds deadline,
                      v1::CameraTakeReport* report) override {
    grpc::ClientContext context;
    SetDeadline(&context, deadline);
    return FromGrpcStatus(stub_->Finish(&context, request, report));
  }

 private:
  static constexpr std::chrono::milliseconds kPoll{1000};
  std::chrono::milliseconds answer_;
  std::unique_ptr<v1::CameraNode::Stub> stub_;
};

class GrpcLightClient final : public LightClient {
 public:
  GrpcLightClient(const std::string& address, std::chrono::milliseconds answer)
      : answer_(answer), stub_(v1::LightNode::NewStub(MakeChannel(address))) {}

  absl::Status Arm(const v1::ArmLightRequest& request, SteadyTime give_up, v1::LightStats* stats) override {
    return Patiently(answer_, give_up, [&](grpc::ClientContext* c) { return stub_->Arm(c, request, stats); });
  }
  absl::Status Heartbeat(const v1::HeartbeatRequest& request, std::chrono::milliseconds deadline,
                         v1::LightStats* stats) override {
    grpc::ClientContext context;
    SetDeadline(&context, deadline);
    return FromGrpcStatus(stub_->Heartbeat(&context, request, stats));
  }
  absl::Status Disarm(const v1::DisarmLightRequest& request, SteadyTime give_up, v1::LightStats* stats) override {
    return Patiently(kDisarm, give_up, [&](grpc::ClientContext* c) { return stub_->Disarm(c, request, stats); });
  }
  absl::Status StartTable(const v1::StartTableRequest& request, SteadyTime give_up) override {
    v1::LightStats stats;
    return Patiently(answer_, give_up, [&](grpc::ClientContext* c) { return stub_->StartTable(c, request, &stats); });
  }

 private:
  static constexpr std::chrono::milliseconds kDisarm{2000};
  std::chrono::milliseconds answer_;
  std::unique_ptr<v1::LightNode::Stub> stub_;
};

}  // namespace

NodeClients GrpcNodeClients(std::chrono::milliseconds answer) {
  NodeClients clients;
  clients.camera = [answer](const v1::CameraConfig& c) -> std::unique_ptr<CameraClient> {
    return std::make_unique<GrpcCameraClient>(c.address(), answer);
  };
  clients.light = [answer](const v1::LightNodeConfig& n) -> std::unique_ptr<LightClient> {
    return std::make_unique<GrpcLightClient>(n.address(), answer);
  };
  return clients;
}

}  // namespace stage::controller
