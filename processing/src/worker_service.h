// gRPC ProcessingWorker service: runs processing stages on a take the worker can read (the same library calls as
// stage-process), streaming their progress.
#pragma once

#include <atomic>
#include <functional>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/photometric_stage.h"
#include "stage/v1/processing_worker.grpc.pb.h"

namespace stage::processing {

class WorkerService final : public v1::ProcessingWorker::Service {
 public:
  WorkerService(std::string id, std::string rig_hash, uint32_t threads)
      : id_(std::move(id)), rig_hash_(std::move(rig_hash)), threads_(threads) {}
  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) override;
  grpc::Status GetWorkerStatus(grpc::ServerContext*, const v1::GetWorkerStatusRequest*,
                               v1::WorkerStatus* response) override;
  // Stages: photometric stereo (the default), calibration, multi-view stereo, the template fit. Errors: InvalidArgument
  // for a bad job (unknown stage, no take directory), and the stage's own error (naming the frame, camera or file)
  // otherwise.
  grpc::Status Process(grpc::ServerContext* context, const v1::ProcessingJob* job,
                       grpc::ServerWriter<v1::ProcessingProgress>* writer) override;

 private:
  // One job of each stage: the final progress message (finished unset), or the stage's error.
  absl::StatusOr<v1::ProcessingProgress> RunPhotometricJob(const v1::ProcessingJob& job,
                                                           const std::function<void(const JobProgress&)>& progress,
                                                           const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunCalibrationJob(const v1::ProcessingJob& job,
                                                           const std::function<void(const JobProgress&)>& progress,
                                                           const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunMvsJob(const v1::ProcessingJob& job,
                                                   const std::function<void(const JobProgress&)>& progress,
                                                   const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunFitJob(const v1::ProcessingJob& job,
                                                   const std::function<void(const JobProgress&)>& progress,
                                                   const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunTexturesJob(const v1::ProcessingJob& job,
                                                        const std::function<void(const JobProgress&)>& progress,
                                                        const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunStabilizeJob(const v1::ProcessingJob& job,
                                                         const std::function<void(const JobProgress&)>& progress,
                                                         const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunAssetDatasetJob(const v1::ProcessingJob& job,
                                                            const std::function<void(const JobProgress&)>& progress,
                                                            const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunAssetTrainJob(const v1::ProcessingJob& job,
                                                          const std::function<void(const JobProgress&)>& progress,
                                                          const std::function<bool()>& cancelled) const;
  absl::StatusOr<v1::ProcessingProgress> RunAssetInferJob(const v1::ProcessingJob& job,
                                                          const std::function<void(const JobProgress&)>& progress,
                                                          const std::function<bool()>& cancelled) const;
  // worker_graph.cc: the processing graph on this machine (the local executor).
  absl::StatusOr<v1::ProcessingProgress> RunGraphJob(const v1::ProcessingJob& job,
                                                     const std::function<void(const JobProgress&)>& progress,
                                                     const std::function<bool()>& cancelled) const;
  std::string id_;
  std::string rig_hash_;
  uint32_t threads_;
  std::atomic<uint64_t> jobs_completed_{0};
  std::atomic<uint64_t> jobs_failed_{0};
  std::mutex mutex_;
  std::vector<const v1::ProcessingJob*> running_;  // guarded by mutex_
};

}  // namespace stage::processing
