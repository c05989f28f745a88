// Suites that run processing jobs on a processing worker as the controller does: a worker started for the job
// (processing-worker on loopback, stopped by its pid after), and the comparison of outputs written three ways.
#pragma once

#include <grpcpp/grpcpp.h>

#include <map>
#include <string>

#include "stage/v1/processing_worker.pb.h"

namespace stage::testing {

// Runs `request` on a processing worker started for it in `dir` (its port file and log there); the RPC's status, and
// the last progress message in `last`.
grpc::Status RunOnWorkerStatus(const std::string& dir, const v1::ProcessingJob& request,
                               v1::ProcessingProgress* last = nullptr);
// The same, failing the calling test when the job fails.
void RunOnWorker(const std::string& dir, const v1::ProcessingJob& request, v1::ProcessingProgress* last);

// The command's files (`batch`, FilesUnder) and those under `dir`: the same names, the same bytes.
void ExpectSameFiles(const std::map<std::string, std::string>& batch, const std::string& dir);

}  // namespace stage::testing
