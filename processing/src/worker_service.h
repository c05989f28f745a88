// gRPC ProcessingWorker service. Processing stages arrive with the photometric-stereo and later issues; today the
// worker reports who it is and that it runs nothing.
#pragma once

#include <atomic>
#include <string>

#include "stage/v1/processing_worker.grpc.pb.h"

namespace stage::processing {

class WorkerService final : public v1::ProcessingWorker::Service {
 public:
  WorkerService(std::string id, std::string rig_hash, uint32_t threads)
      : id_(std::move(id)), rig_hash_(std::move(rig_hash)), threads_(threads) {}
  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) override;
  grpc::Status GetWorkerStatus(grpc::ServerContext*, const v1::GetWorkerStatusRequest*,
                               v1::WorkerStatus* response) override;

 private:
  std::string id_;
  std::string rig_hash_;
  uint32_t threads_;
  std::atomic<uint64_t> jobs_completed_{0};
  std::atomic<uint64_t> jobs_failed_{0};
};

}  // namespace stage::processing
