// StageController through a real server on loopback: GetStageStatus counts nodes by state, WatchStageStatus sends a
// snapshot at once and another when a node goes down.
#include "controller_service.h"

#include <grpcpp/grpcpp.h>

#include <thread>

#include "gtest/gtest.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/v1/processing_worker.grpc.pb.h"

namespace stage::controller {
namespace {

// A worker node on a real port: the simplest node there is.
class FakeWorker final : public v1::ProcessingWorker::Service {
 public:
  grpc::Status GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* info) override {
    info->set_id("worker-1");
    info->set_version("test");
    return grpc::Status::OK;
  }
};

TEST(ControllerServiceTest, StatusAndWatch) {
  FakeWorker worker;
  auto worker_server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&worker});
  ASSERT_TRUE(worker_server.ok());
  v1::RigConfig rig;
  rig.mutable_stage()->set_id("s");
  rig.mutable_stage()->set_name("Stage");
  auto* w = rig.add_processing_workers();
  w->set_id("worker-1");
  w->set_address((*worker_server)->address());
  ApplyRigDefaults(&rig);
  LoadedRig loaded;
  loaded.rig = rig;

  HealthMonitor monitor(TargetsFromRig(rig), {std::chrono::milliseconds(50), std::chrono::milliseconds(300)});
  monitor.Start();
  ControllerService service(loaded, &monitor);
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&service});
  ASSERT_TRUE(server.ok());
  auto stub = v1::StageController::NewStub(MakeChannel((*server)->address()));

  // GetStageStatus: the worker comes up.
  v1::StageStatus status;
  for (int i = 0; i < 200 && status.nodes_up() != 1; ++i) {
    grpc::ClientContext context;
    ASSERT_TRUE(stub->GetStageStatus(&context, v1::GetStageStatusRequest(), &status).ok());
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_EQ(status.nodes_up(), 1);
  EXPECT_EQ(status.nodes_total(), 1);
  EXPECT_EQ(status.stage_id(), "s");
  EXPECT_EQ(status.nodes(0).version(), "test");
  EXPECT_EQ(status.controller().kind(), v1::NODE_KIND_CONTROLLER);
  // A rig without cameras or lights still has a (trivial) schedule; the verifier says it cannot record a take (no
  // camera, no light node).
  EXPECT_EQ(status.schedule_hash().size(), 16u);
  EXPECT_EQ(status.timing_errors(), 2);

  // WatchStageStatus: a snapshot at once, then one showing the worker down after it stops.
  grpc::ClientContext watch_context;
  v1::WatchStageStatusRequest request;
  request.set_heartbeat_ms(60000);  // only changes, no heartbeats, within this test
  auto reader = stub->WatchStageStatus(&watch_context, request);
  v1::StageStatus update;
  ASSERT_TRUE(reader->Read(&update));
  EXPECT_EQ(update.nodes_up(), 1);
  (*worker_server)->Shutdown();
  ASSERT_TRUE(reader->Read(&update));
  EXPECT_EQ(update.nodes_up(), 0);
  EXPECT_EQ(update.nodes(0).state(), v1::NODE_STATE_DOWN);
  watch_context.TryCancel();
  monitor.Stop();
}

// The timing RPCs verify and export the live rig, with what-if overrides.
TEST(ControllerServiceTest, TimingCheckAndExportOnTheLiveRig) {
  auto rig = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(rig.ok());
  HealthMonitor monitor({}, {});
  ControllerService service(*rig, &monitor);
  EXPECT_EQ(service.timing().errors(), 0);
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&service});
  ASSERT_TRUE(server.ok());
  auto stub = v1::StageController::NewStub(MakeChannel((*server)->address()));

  v1::TimingQuery query;
  v1::TimingReport report;
  {
    grpc::ClientContext context;
    ASSERT_TRUE(stub->CheckTiming(&context, query, &report).ok());
  }
  EXPECT_EQ(report.errors(), 0);
  EXPECT_EQ(report.schedule().hash(), service.Status().schedule_hash());

  // What if hs-1 were triggered 40 us after the edge?
  query.add_overrides("cameras[hs-1].trigger.delay_us=40");
  {
    grpc::ClientContext context;
    ASSERT_TRUE(stub->CheckTiming(&context, query, &report).ok());
  }
  ASSERT_EQ(report.errors(), 1);
  EXPECT_EQ(report.violations(0).check(), "steady-light");
  EXPECT_EQ(report.violations(0).device(), "hs-1");
  EXPECT_NE(report.schedule().hash(), service.Status().schedule_hash());

  // A bad override is the caller's error, named.
  query.set_overrides(0, "cameras[hs-9].exposure_us=1");
  {
    grpc::ClientContext context;
    grpc::Status s = stub->CheckTiming(&context, query, &report);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(s.error_message().find("hs-9"), std::string::npos) << s.error_message();
  }

  v1::TimingExportRequest request;
  request.set_vcd(true);
  request.set_svg(true);
  request.set_json(true);
  v1::TimingExport out;
  {
    grpc::ClientContext context;
    ASSERT_TRUE(stub->ExportTiming(&context, request, &out).ok());
  }
  EXPECT_EQ(out.slot_count(), 38);
  EXPECT_NE(out.vcd().find("$timescale 1 ns $end"), std::string::npos);
  EXPECT_NE(out.svg().find("<svg"), std::string::npos);
  EXPECT_NE(out.json().find("\"pattern_name\": \"parallel-full\""), std::string::npos);
  request.set_slot_count(38);
  request.set_first_slot(150'000'000'000);  // past the 64-bit tick range (about five years of slots)
  {
    grpc::ClientContext context;
    grpc::Status s = stub->ExportTiming(&context, request, &out);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(s.error_message().find("beyond the exact time base"), std::string::npos) << s.error_message();
  }
  request.set_first_slot(0);
  request.set_slot_count(1'000'000);
  {
    grpc::ClientContext context;
    EXPECT_EQ(stub->ExportTiming(&context, request, &out).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  }
}

}  // namespace
}  // namespace stage::controller
