// Processing jobs on a worker started for them: see worker_support.h.
#include "worker_support.h"

#include <chrono>
#include <filesystem>
#include <thread>

#include "gtest/gtest.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/subprocess.h"
#include "stage/v1/processing_worker.grpc.pb.h"
#include "test_support.h"

namespace stage::testing {

namespace fs = std::filesystem;

// Runs `request` on a processing worker started for it; the RPC's status, the last progress message in `last`.
grpc::Status RunOnWorkerStatus(const std::string& dir, const v1::ProcessingJob& request, v1::ProcessingProgress* last) {
  const std::string port_file = dir + "/worker.port";
  fs::remove(port_file);
  auto worker = Subprocess::Spawn({.argv = {BinDir() + "/processing-worker", "--id", "worker-1", "--listen",
                                            "127.0.0.1:0", "--port-file", port_file},
                                   .stderr_path = dir + "/worker.log"});
  if (!worker.ok()) return grpc::Status(grpc::StatusCode::INTERNAL, std::string(worker.status().message()));
  for (int i = 0; i < 1000 && !fs::exists(port_file); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  if (!fs::exists(port_file)) {
    (*worker)->Terminate(std::chrono::milliseconds(2000));
    return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the worker wrote no port: " + ReadFile(dir + "/worker.log"));
  }
  auto stub = v1::ProcessingWorker::NewStub(MakeChannel(ReadFile(port_file)));
  grpc::ClientContext context;
  auto reader = stub->Process(&context, request);
  v1::ProcessingProgress progress;
  while (reader->Read(&progress)) {
    if (last != nullptr) *last = progress;
  }
  const grpc::Status rpc = reader->Finish();
  (*worker)->Terminate(std::chrono::milliseconds(2000));
  return rpc;
}

void RunOnWorker(const std::string& dir, const v1::ProcessingJob& request, v1::ProcessingProgress* last) {
  const grpc::Status rpc = RunOnWorkerStatus(dir, request, last);
  ASSERT_TRUE(rpc.ok()) << rpc.error_message();
}

// The command's files (`batch`, FilesUnder) and those under `dir`: the same names, the same bytes.
void ExpectSameFiles(const std::map<std::string, std::string>& batch, const std::string& dir) {
  const auto b = FilesUnder(dir);
  ASSERT_EQ(b.size(), batch.size()) << dir;
  for (const auto& [name, bytes] : batch) {
    ASSERT_EQ(b.count(name), 1u) << name;
    EXPECT_TRUE(bytes == b.at(name)) << name << " differs between the command and " << dir;
  }
}

}  // namespace stage::testing
