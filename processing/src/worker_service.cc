// gRPC ProcessingWorker service.
#include "worker_service.h"

#include "stage/common/node_info.h"

namespace stage::processing {

grpc::Status WorkerService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = MakeNodeInfo(id_, v1::NODE_KIND_PROCESSING_WORKER, "", "local", rig_hash_);
  return grpc::Status::OK;
}

grpc::Status WorkerService::GetWorkerStatus(grpc::ServerContext*, const v1::GetWorkerStatusRequest*,
                                            v1::WorkerStatus* response) {
  response->set_jobs_completed(jobs_completed_.load());
  response->set_jobs_failed(jobs_failed_.load());
  response->set_threads(threads_);
  return grpc::Status::OK;
}

}  // namespace stage::processing
