#include "device_monitor.h"

#include <grpcpp/grpcpp.h>

#include <utility>

#include "stage/common/clock.h"
#include "stage/common/grpc_call.h"
#include "stage/common/grpc_status.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage::controller {
namespace {

// What of a device the stage shows as its state: a change wakes the watchers; counters and temperatures do not.
std::string ShownState(const v1::NodeDevice& d) {
  std::string s = d.error().empty() ? "ok" : "error";
  if (d.has_light()) s += "/" + v1::LightMode_Name(d.light().mode()) + "/" + std::to_string(d.light().faults_size());
  if (d.has_camera()) s += d.camera().link_up() ? "/link" : "/nolink";
  return s;
}

}  // namespace

absl::Status DeviceMonitorOptions::Validate() const {
  if (interval.count() <= 0) return absl::InvalidArgumentError("device monitor: interval must be positive");
  if (timeout.count() <= 0) return absl::InvalidArgumentError("device monitor: timeout must be positive");
  return absl::OkStatus();
}

DeviceMonitor::DeviceMonitor(std::vector<DeviceTarget> targets, DeviceMonitorOptions options,
                             std::function<void()> on_change)
    : targets_(std::move(targets)), options_(options), on_change_(std::move(on_change)) {
  for (const DeviceTarget& t : targets_) {
    v1::NodeDevice& d = devices_.emplace_back();
    d.set_id(t.id);
    d.set_kind(t.kind);
  }
}

DeviceMonitor::~DeviceMonitor() { Stop(); }

void DeviceMonitor::Start() {
  for (size_t i = 0; i < targets_.size(); ++i) threads_.emplace_back([this, i] { Read(i); });
}

void DeviceMonitor::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  stop_.notify_all();
  for (auto& t : threads_) {
    if (t.joinable()) t.join();
  }
  threads_.clear();
}

std::vector<v1::NodeDevice> DeviceMonitor::Snapshot() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return devices_;
}

void DeviceMonitor::Read(size_t index) {
  const DeviceTarget& target = targets_[index];
  auto next = std::chrono::steady_clock::now();
  while (true) {
    v1::NodeDevice read;
    const absl::Status status = target.read(options_.timeout, &read);
    bool changed = false;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) return;
      v1::NodeDevice& d = devices_[index];
      const std::string before = ShownState(d);
      if (status.ok()) {
        read.set_id(target.id);
        read.set_kind(target.kind);
        read.set_read_unix_ns(UnixNowNs());
        d = std::move(read);
      } else {
        d.set_error(std::string(status.message()));  // the last good read stays, with its time
      }
      changed = ShownState(d) != before;
    }
    if (changed && on_change_) on_change_();
    next += options_.interval;
    std::unique_lock<std::mutex> lock(mutex_);
    if (stop_.wait_until(lock, next, [&] { return stopping_; })) return;
  }
}

std::vector<DeviceTarget> DeviceTargetsFromRig(const v1::RigConfig& rig) {
  std::vector<DeviceTarget> targets;
  for (const v1::CameraConfig& c : rig.cameras()) {
    auto stub = std::shared_ptr<v1::CameraNode::Stub>(v1::CameraNode::NewStub(MakeChannel(c.address())));
    targets.push_back({c.id(), v1::NODE_KIND_CAMERA, [stub](std::chrono::milliseconds deadline, v1::NodeDevice* d) {
                         grpc::ClientContext context;
                         SetDeadline(&context, deadline);
                         return FromGrpcStatus(stub->GetStats(&context, v1::GetStatsRequest(), d->mutable_camera()));
                       }});
  }
  for (const v1::LightNodeConfig& n : rig.light_nodes()) {
    auto stub = std::shared_ptr<v1::LightNode::Stub>(v1::LightNode::NewStub(MakeChannel(n.address())));
    targets.push_back({n.id(), v1::NODE_KIND_LIGHT, [stub](std::chrono::milliseconds deadline, v1::NodeDevice* d) {
                         grpc::ClientContext context;
                         SetDeadline(&context, deadline);
                         return FromGrpcStatus(
                             stub->GetStats(&context, v1::GetLightStatsRequest(), d->mutable_light()));
                       }});
  }
  return targets;
}

}  // namespace stage::controller
