// The SimWorld gRPC service: the world shared by the simulated stage's processes. A device's Join stream stays open
// while it lives; when the stream ends (the device left, or its process died) the world lets it go.
#pragma once

#include <atomic>
#include <functional>
#include <map>
#include <mutex>

#include "stage/sim/world.h"
#include "stage/v1/sim.grpc.pb.h"

namespace stage::sim {

class WorldService final : public v1::SimWorld::Service {
 public:
  // `world` is not owned and must outlive the service. `check_fault`, if given, vets an injected fault first (that
  // its fields apply to its target, in range), so that the message names the field.
  WorldService(World* world, v1::WorldInfo info, std::function<absl::Status(const v1::SimFault&)> check_fault = nullptr)
      : world_(world), info_(std::move(info)), check_fault_(std::move(check_fault)) {}
  grpc::Status Join(grpc::ServerContext* context, const v1::JoinWorldRequest* request,
                    grpc::ServerWriter<v1::JoinWorldEvent>* writer) override;
  grpc::Status WaitForEdge(grpc::ServerContext*, const v1::WaitForEdgeRequest* request,
                           v1::WorldEdgeEvent* response) override;
  grpc::Status Done(grpc::ServerContext*, const v1::WorldDoneRequest* request, v1::WorldAck*) override;
  grpc::Status ReportLevels(grpc::ServerContext*, const v1::ReportLevelsRequest* request, v1::WorldAck*) override;
  grpc::Status Exposure(grpc::ServerContext*, const v1::ExposureRequest* request,
                        v1::ExposureLevels* response) override;
  grpc::Status InjectFault(grpc::ServerContext*, const v1::SimFault* request, v1::WorldAck*) override;
  grpc::Status Run(grpc::ServerContext*, const v1::RunWorldRequest* request, v1::WorldRunReply* reply) override;
  grpc::Status EndRun(grpc::ServerContext*, const v1::EndRunRequest* request, v1::WorldRunReply* reply) override;
  grpc::Status GetRun(grpc::ServerContext*, const v1::GetRunRequest* request, v1::WorldRunReply* reply) override;
  grpc::Status WriteGroundTruth(grpc::ServerContext*, const v1::GroundTruthRequest* request,
                                v1::GroundTruthReply* reply) override;
  // Who writes ground truth (the process that holds the scene); without it WriteGroundTruth is UNIMPLEMENTED.
  void set_ground_truth_writer(std::function<absl::Status(const v1::GroundTruthRequest&)> writer) {
    ground_truth_ = std::move(writer);
  }

  // Ends every Join stream (for shutdown).
  void Shutdown();

 private:
  void FillRunReply(const WorldRun& run, v1::WorldRunReply* reply) const;
  void CountBusCall(const std::string& caller);

  World* world_;
  v1::WorldInfo info_;
  std::function<absl::Status(const v1::SimFault&)> check_fault_;
  std::function<absl::Status(const v1::GroundTruthRequest&)> ground_truth_;
  std::atomic<bool> shutting_down_{false};
  mutable std::mutex bus_calls_mutex_;
  std::map<std::string, int64_t> bus_calls_;  // guarded by bus_calls_mutex_
};

}  // namespace stage::sim
