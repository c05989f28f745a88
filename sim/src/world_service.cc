// The SimWorld service and its clients.
#include "stage/sim/world_service.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <chrono>
#include <mutex>
#include <thread>

#include "absl/strings/str_cat.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/sim/world_client.h"

namespace stage::sim {

// ---- service -------------------------------------------------------------------------------------------------------

grpc::Status WorldService::Join(grpc::ServerContext* context, const v1::JoinWorldRequest* request,
                                grpc::ServerWriter<v1::JoinWorldEvent>* writer) {
  const int device = world_->Register(request->name(), request->light_node());
  v1::JoinWorldEvent event;
  event.set_device(device);
  *event.mutable_info() = info_;
  if (writer->Write(event)) {
    // The device is there while its stream is open.
    while (!context->IsCancelled() && !shutting_down_.load()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  }
  world_->Unregister(device);
  return grpc::Status::OK;
}

void WorldService::Shutdown() { shutting_down_.store(true); }

grpc::Status WorldService::WaitForEdge(grpc::ServerContext*, const v1::WaitForEdgeRequest* request,
                                       v1::WorldEdgeEvent* response) {
  auto edge = world_->WaitForEdge(request->device(), request->slot());
  if (!edge) {
    response->set_stopped(true);
    return grpc::Status::OK;
  }
  response->set_slot(edge->slot);
  response->set_time_ns(edge->time_ns);
  response->set_missed(edge->missed);
  for (auto& f : edge->faults) *response->add_faults() = std::move(f);
  response->set_run_first(edge->run.first);
  response->set_run_end(edge->run.end);
  return grpc::Status::OK;
}

grpc::Status WorldService::Run(grpc::ServerContext*, const v1::RunWorldRequest* request, v1::WorldRunReply* reply) {
  CountBusCall(request->requested_by());
  absl::StatusOr<WorldRun> run;
  if (request->first_slot() > 0 && !request->plan_only()) {
    run = WorldRun{request->first_slot(), request->first_slot() + request->slots(), request->requested_by()};
    if (absl::Status s = world_->StartRun(*run); !s.ok()) return ToGrpcStatus(s);
  } else {
    run = world_->PlanRun(request->slots(), request->lead_slots(), std::max<int64_t>(1, request->align_slots()),
                          request->min_first_slot());
    if (run.ok() && !request->plan_only()) {
      run->driver = request->requested_by();
      if (absl::Status s = world_->StartRun(*run); !s.ok()) return ToGrpcStatus(s);
    }
  }
  if (!run.ok()) return ToGrpcStatus(run.status());
  FillRunReply(*run, reply);
  return grpc::Status::OK;
}

grpc::Status WorldService::EndRun(grpc::ServerContext*, const v1::EndRunRequest* request, v1::WorldRunReply* reply) {
  CountBusCall(request->requested_by());
  auto run = world_->EndRun(request->align_slots());
  if (!run.ok()) return ToGrpcStatus(run.status());
  FillRunReply(*run, reply);
  return grpc::Status::OK;
}

grpc::Status WorldService::GetRun(grpc::ServerContext*, const v1::GetRunRequest* request, v1::WorldRunReply* reply) {
  CountBusCall(request->requested_by());
  const std::optional<WorldRun> run = world_->LastRun();
  if (!run) return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "the bus has had no run yet");
  FillRunReply(*run, reply);
  return grpc::Status::OK;
}

void WorldService::FillRunReply(const WorldRun& run, v1::WorldRunReply* reply) const {
  reply->set_first_slot(run.first);
  reply->set_end_slot(run.end);
  reply->set_first_edge_ns(world_->EdgeNs(run.first));
  reply->set_current_slot(world_->current_slot());
  reply->set_started_by(run.driver);
  std::lock_guard<std::mutex> lock(bus_calls_mutex_);
  reply->mutable_bus_calls()->insert(bus_calls_.begin(), bus_calls_.end());
}

void WorldService::CountBusCall(const std::string& caller) {
  std::lock_guard<std::mutex> lock(bus_calls_mutex_);
  ++bus_calls_[caller];
}

grpc::Status WorldService::WriteGroundTruth(grpc::ServerContext*, const v1::GroundTruthRequest* request,
                                            v1::GroundTruthReply* reply) {
  if (!ground_truth_) return grpc::Status(grpc::StatusCode::UNIMPLEMENTED, "this world writes no ground truth");
  const auto start = std::chrono::steady_clock::now();
  if (absl::Status s = ground_truth_(*request); !s.ok()) return ToGrpcStatus(s);
  reply->set_frames(request->frames());
  reply->set_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  return grpc::Status::OK;
}

grpc::Status WorldService::InjectFault(grpc::ServerContext*, const v1::SimFault* request, v1::WorldAck*) {
  if (check_fault_) {
    if (absl::Status s = check_fault_(*request); !s.ok()) return ToGrpcStatus(s);
  }
  return ToGrpcStatus(world_->InjectFault(*request));
}

grpc::Status WorldService::Done(grpc::ServerContext*, const v1::WorldDoneRequest* request, v1::WorldAck*) {
  world_->Done(request->device(), request->slot());
  return grpc::Status::OK;
}

grpc::Status WorldService::ReportLevels(grpc::ServerContext*, const v1::ReportLevelsRequest* request, v1::WorldAck*) {
  std::vector<double> levels(request->levels().begin(), request->levels().end());
  world_->ReportLevels(request->light_node(), request->time_ns(), levels, request->watermark_ns());
  return grpc::Status::OK;
}

grpc::Status WorldService::Exposure(grpc::ServerContext*, const v1::ExposureRequest* request,
                                    v1::ExposureLevels* response) {
  auto levels = world_->Exposure(request->t0_ns(), request->t1_ns());
  if (!levels.ok()) {
    if (absl::IsCancelled(levels.status())) {
      response->set_stopped(true);
    } else {
      response->set_error(std::string(levels.status().message()));
    }
    return grpc::Status::OK;
  }
  response->mutable_cross()->Assign(levels->cross.data(), levels->cross.data() + levels->cross.size());
  response->mutable_parallel()->Assign(levels->parallel.data(), levels->parallel.data() + levels->parallel.size());
  return grpc::Status::OK;
}

// ---- clients -------------------------------------------------------------------------------------------------------

namespace {

class Local final : public WorldClient {
 public:
  explicit Local(World* world) : world_(world) {}
  absl::StatusOr<int> Join(const std::string& name, int light_node) override {
    return world_->Register(name, light_node);
  }
  uint32_t slot_rate_hz() const override { return world_->base().slot_rate_hz(); }
  bool lockstep() const override { return true; }
  int64_t t0_ns() const override { return world_->EdgeNs(0); }
  std::optional<WorldEdge> WaitForEdge(int device, int64_t slot) override { return world_->WaitForEdge(device, slot); }
  void Done(int device, int64_t slot) override { world_->Done(device, slot); }
  void ReportLevels(int node, int64_t t, const std::vector<double>& levels, int64_t watermark) override {
    world_->ReportLevels(node, t, levels, watermark);
  }
  absl::StatusOr<EmitterLevels> Exposure(int64_t t0, int64_t t1) override { return world_->Exposure(t0, t1); }
  void Leave(int device) override { world_->Unregister(device); }

 private:
  World* world_;
};

class Remote final : public WorldClient {
 public:
  explicit Remote(std::shared_ptr<grpc::Channel> channel)
      : channel_(std::move(channel)), stub_(v1::SimWorld::NewStub(channel_)) {}
  ~Remote() override {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto& j : joins_) {
      j->context.TryCancel();
      if (j->reader.joinable()) j->reader.join();
    }
  }

  absl::StatusOr<int> Join(const std::string& name, int light_node) override {
    auto join = std::make_unique<JoinStream>();
    v1::JoinWorldRequest request;
    request.set_name(name);
    request.set_light_node(light_node);
    join->stream = stub_->Join(&join->context, request);
    v1::JoinWorldEvent event;
    if (!join->stream->Read(&event)) {
      grpc::Status s = join->stream->Finish();
      return absl::UnavailableError(absl::StrCat("the simulated world did not take ", name, ": ", s.error_message()));
    }
    info_ = event.info();
    const int device = event.device();
    JoinStream* raw = join.get();
    // Keep the stream open (the world's sign that the device lives) until Leave() or destruction.
    raw->reader = std::thread([raw] {
      v1::JoinWorldEvent ignored;
      while (raw->stream->Read(&ignored)) {
      }
      (void)raw->stream->Finish();
    });
    raw->device = device;
    std::lock_guard<std::mutex> lock(mutex_);
    joins_.push_back(std::move(join));
    return device;
  }
  uint32_t slot_rate_hz() const override { return info_.slot_rate_hz(); }
  bool lockstep() const override { return info_.lockstep(); }
  int64_t t0_ns() const override { return info_.t0_ns(); }

  std::optional<WorldEdge> WaitForEdge(int device, int64_t slot) override {
    grpc::ClientContext context;
    v1::WaitForEdgeRequest request;
    request.set_device(device);
    request.set_slot(slot);
    v1::WorldEdgeEvent edge;
    if (!stub_->WaitForEdge(&context, request, &edge).ok() || edge.stopped()) return std::nullopt;
    return WorldEdge{edge.slot(),
                     edge.time_ns(),
                     edge.missed(),
                     {edge.faults().begin(), edge.faults().end()},
                     WorldRun{edge.run_first(), edge.run_end()}};
  }
  void Done(int device, int64_t slot) override {
    grpc::ClientContext context;
    v1::WorldDoneRequest request;
    request.set_device(device);
    request.set_slot(slot);
    v1::WorldAck ack;
    (void)stub_->Done(&context, request, &ack);
  }
  void ReportLevels(int node, int64_t t, const std::vector<double>& levels, int64_t watermark) override {
    grpc::ClientContext context;
    v1::ReportLevelsRequest request;
    request.set_light_node(node);
    request.set_time_ns(t);
    for (double l : levels) request.add_levels(static_cast<float>(l));
    request.set_watermark_ns(watermark);
    v1::WorldAck ack;
    (void)stub_->ReportLevels(&context, request, &ack);
  }
  absl::StatusOr<EmitterLevels> Exposure(int64_t t0, int64_t t1) override {
    grpc::ClientContext context;
    v1::ExposureRequest request;
    request.set_t0_ns(t0);
    request.set_t1_ns(t1);
    v1::ExposureLevels response;
    grpc::Status status = stub_->Exposure(&context, request, &response);
    if (!status.ok()) {
      return absl::CancelledError(absl::StrCat("the simulated world is gone: ", status.error_message()));
    }
    if (response.stopped()) return absl::CancelledError("the simulated world stopped");
    if (!response.error().empty()) return absl::OutOfRangeError(response.error());
    EmitterLevels levels{Eigen::Map<const Eigen::VectorXf>(response.cross().data(), response.cross_size()),
                         Eigen::Map<const Eigen::VectorXf>(response.parallel().data(), response.parallel_size())};
    return levels;
  }
  void Leave(int device) override {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto& j : joins_) {
      if (j->device == device) j->context.TryCancel();
    }
  }

 private:
  struct JoinStream {
    grpc::ClientContext context;
    std::unique_ptr<grpc::ClientReader<v1::JoinWorldEvent>> stream;
    std::thread reader;
    int device = -1;
  };
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::SimWorld::Stub> stub_;
  v1::WorldInfo info_;
  std::mutex mutex_;
  std::vector<std::unique_ptr<JoinStream>> joins_;  // guarded by mutex_
};

}  // namespace

std::unique_ptr<WorldClient> LocalWorldClient(World* world) { return std::make_unique<Local>(world); }

absl::StatusOr<std::unique_ptr<WorldClient>> ConnectWorld(const std::string& address) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(64 << 20);
  auto channel = MakeChannel(address, args);
  if (!channel->WaitForConnected(std::chrono::system_clock::now() + std::chrono::seconds(10))) {
    return absl::UnavailableError(absl::StrCat("the simulated world at ", address, " does not answer"));
  }
  return std::unique_ptr<WorldClient>(new Remote(std::move(channel)));
}

}  // namespace stage::sim
