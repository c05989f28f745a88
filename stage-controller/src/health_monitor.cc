// Health polling of the stage's nodes.
#include "health_monitor.h"

#include <grpcpp/grpcpp.h>

#include "absl/strings/str_cat.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "stage/common/clock.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
#include "stage/common/rpc_channel.h"
#include "stage/timing/clock_sync.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "stage/v1/node.grpc.pb.h"
#include "stage/v1/processing_worker.grpc.pb.h"

namespace stage::controller {
namespace {

// GetInfo through the service of the node's kind.
grpc::Status CallGetInfo(v1::NodeKind kind, const std::shared_ptr<grpc::Channel>& channel,
                         std::chrono::system_clock::time_point deadline, v1::NodeInfo* info) {
  grpc::ClientContext context;
  context.set_deadline(deadline);
  v1::GetInfoRequest request;
  switch (kind) {
    case v1::NODE_KIND_CAMERA:
      return v1::CameraNode::NewStub(channel)->GetInfo(&context, request, info);
    case v1::NODE_KIND_LIGHT:
      return v1::LightNode::NewStub(channel)->GetInfo(&context, request, info);
    case v1::NODE_KIND_PROCESSING_WORKER:
      return v1::ProcessingWorker::NewStub(channel)->GetInfo(&context, request, info);
    default:
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "no GetInfo for this node kind");
  }
}

// True when the transport says plainly that no process serves the address (refused, or the connection was closed or
// reset under the call: a crashed or killed node). Other transport failures (a peer that accepts TCP but never
// completes the HTTP/2 handshake, routing errors) mean the node may exist but cannot be reached. gRPC reports both as
// UNAVAILABLE and tells them apart only in words; health_monitor_test pins these words against real peers.
bool IsNothingListening(const grpc::Status& rpc) {
  if (rpc.error_code() != grpc::StatusCode::UNAVAILABLE) return true;
  const std::string& m = rpc.error_message();
  for (const char* word : {"Connection refused", "Socket closed", "Connection reset", "Broken pipe", "End of TCP"}) {
    if (m.find(word) != std::string::npos) return true;
  }
  return false;
}

}  // namespace

struct HealthMonitor::Node {
  NodeTarget target;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<grpc::health::v1::Health::Stub> health;
  std::unique_ptr<v1::NodeClock::Stub> clock;
  v1::NodeStatus status;  // guarded by HealthMonitor::mutex_
  // When the last GetInfo answered, to extrapolate uptime without asking every poll.
  std::chrono::steady_clock::time_point info_time;
  // Poller thread only.
  timing::ClockEstimator estimator;
  std::chrono::steady_clock::time_point next_sync;
};

HealthMonitor::HealthMonitor(std::vector<NodeTarget> targets, HealthMonitorOptions options) : options_(options) {
  for (NodeTarget& t : targets) {
    auto node = std::make_unique<Node>();
    grpc::ChannelArguments args;
    // Come back quickly after a node restarts: the default backoff grows to two minutes.
    args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 100);
    args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 100);
    args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
    // One connection per node, not shared with other channels to the same address.
    args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
    node->channel = MakeChannel(t.address, args);
    node->health = grpc::health::v1::Health::NewStub(node->channel);
    node->clock = v1::NodeClock::NewStub(node->channel);
    node->status.set_id(t.id);
    node->status.set_kind(t.kind);
    node->status.set_camera_role(t.role);
    node->status.set_address(t.address);
    node->status.set_state(v1::NODE_STATE_UNKNOWN);
    node->status.set_reason("not polled yet");
    node->status.set_state_since_unix_ns(UnixNowNs());
    node->status.mutable_clock()->set_limit_ns(t.clock_limit_ns);
    node->status.mutable_clock()->set_limit_reason(t.clock_limit_reason);
    node->status.mutable_clock()->set_flagged(t.clock_required);
    node->target = std::move(t);
    nodes_.push_back(std::move(node));
  }
}

HealthMonitor::~HealthMonitor() { Stop(); }

void HealthMonitor::Start() {
  // Spread the nodes' clock measurements over the interval: bursts from every node at once would queue behind each
  // other and inflate every round trip.
  const auto now = std::chrono::steady_clock::now();
  for (size_t i = 0; i < nodes_.size(); ++i) {
    nodes_[i]->next_sync = now + options_.clock_sync_interval * i / std::max<size_t>(1, nodes_.size());
  }
  for (size_t i = 0; i < nodes_.size(); ++i) threads_.emplace_back([this, i] { Poll(i); });
}

void HealthMonitor::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  changed_.notify_all();
  stop_.notify_all();
  for (std::thread& t : threads_) {
    if (t.joinable()) t.join();
  }
  threads_.clear();
}

std::vector<v1::NodeStatus> HealthMonitor::Snapshot() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<v1::NodeStatus> out;
  out.reserve(nodes_.size());
  auto now = std::chrono::steady_clock::now();
  for (const auto& node : nodes_) {
    out.push_back(node->status);
    if (node->status.state() == v1::NODE_STATE_UP) {
      out.back().set_uptime_ns(node->status.uptime_ns() +
                               std::chrono::duration_cast<std::chrono::nanoseconds>(now - node->info_time).count());
    }
  }
  return out;
}

uint64_t HealthMonitor::generation() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return generation_;
}

void HealthMonitor::NotifyChange() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    ++generation_;
  }
  changed_.notify_all();
}

uint64_t HealthMonitor::WaitForChange(uint64_t seen, std::chrono::milliseconds timeout) const {
  std::unique_lock<std::mutex> lock(mutex_);
  changed_.wait_for(lock, timeout, [&] { return generation_ != seen || stopping_; });
  return generation_;
}

void HealthMonitor::Poll(size_t index) {
  Node& node = *nodes_[index];
  auto log = Logger("controller.health");
  auto next = std::chrono::steady_clock::now();
  while (true) {
    {
      std::unique_lock<std::mutex> lock(mutex_);
      if (stop_.wait_until(lock, next, [&] { return stopping_; })) return;
    }
    next += options_.poll_interval;
    auto now = std::chrono::steady_clock::now();
    if (next < now) next = now;  // a slow poll does not cause a burst of catch-up polls

    grpc::ClientContext context;
    auto deadline = std::chrono::system_clock::now() + options_.timeout;
    context.set_deadline(deadline);
    grpc::health::v1::HealthCheckRequest request;
    grpc::health::v1::HealthCheckResponse response;
    auto sent = std::chrono::steady_clock::now();
    grpc::Status rpc = node.health->Check(&context, request, &response);
    auto rtt = std::chrono::steady_clock::now() - sent;

    v1::NodeState state;
    std::string reason;
    if (rpc.ok() && response.status() == grpc::health::v1::HealthCheckResponse::SERVING) {
      state = v1::NODE_STATE_UP;
    } else if (rpc.ok()) {
      state = v1::NODE_STATE_DOWN;
      reason = "the node reports it is not serving";
    } else if (rpc.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED) {
      state = v1::NODE_STATE_UNREACHABLE;
      reason = absl::StrCat("no answer within ", options_.timeout.count(), " ms");
    } else {
      state = IsNothingListening(rpc) ? v1::NODE_STATE_DOWN : v1::NODE_STATE_UNREACHABLE;
      reason = rpc.error_message();
    }

    // Ask who the node is when it comes up (a restarted node may be another version).
    v1::NodeInfo info;
    bool have_info = false;
    bool was_up;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      was_up = node.status.state() == v1::NODE_STATE_UP;
    }
    if (state == v1::NODE_STATE_UP && !was_up) {
      // A node that comes (back) up may be another process with another clock: measure it afresh, now.
      node.estimator = timing::ClockEstimator();
      node.next_sync = {};
      auto info_sent = std::chrono::steady_clock::now();
      grpc::Status s = CallGetInfo(node.target.kind, node.channel, deadline, &info);
      // The health check that found the node up also paid for connecting; GetInfo, on the warm connection, is the
      // round trip an operator should see.
      rtt = std::chrono::steady_clock::now() - info_sent;
      if (s.ok()) {
        have_info = true;
        if (info.id() != node.target.id) {
          state = v1::NODE_STATE_DOWN;
          reason = absl::StrCat("another node answers at ", node.target.address, ": \"", info.id(), "\"");
          have_info = false;
        }
      } else {
        state =
            s.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED ? v1::NODE_STATE_UNREACHABLE : v1::NODE_STATE_DOWN;
        reason = absl::StrCat("GetInfo failed: ", s.error_message());
      }
    }

    {
      std::lock_guard<std::mutex> lock(mutex_);
      v1::NodeStatus& status = node.status;
      bool changed = status.state() != state || status.reason() != reason;
      if (status.state() != state) {
        status.set_state_since_unix_ns(UnixNowNs());
        // Whatever was measured belonged to the process that was up; it says nothing about the next one.
        status.mutable_clock()->set_measured(false);
        status.mutable_clock()->set_flagged(node.target.clock_required);
        if (state == v1::NODE_STATE_UP) {
          log->info("{} ({} at {}) is up", node.target.id, NodeKindName(node.target.kind), node.target.address);
        } else if (status.state() != v1::NODE_STATE_UNKNOWN || state != v1::NODE_STATE_DOWN) {
          log->warn("{} ({} at {}) is {}: {}", node.target.id, NodeKindName(node.target.kind), node.target.address,
                    NodeStateName(state), reason);
        }
      }
      status.set_state(state);
      status.set_reason(reason);
      if (state == v1::NODE_STATE_UP) {
        status.set_last_seen_unix_ns(UnixNowNs());
        status.set_rtt_ns(std::chrono::duration_cast<std::chrono::nanoseconds>(rtt).count());
      }
      if (have_info) {
        changed = changed || status.version() != info.version();
        status.set_version(info.version());
        status.set_backend(info.backend());
        status.set_pid(info.pid());
        status.set_uptime_ns(info.uptime_ns());
        node.info_time = std::chrono::steady_clock::now();
      }
      if (changed) {
        ++generation_;
        changed_.notify_all();
      }
    }  // the status lock
    if (state == v1::NODE_STATE_UP && options_.clock_sync_interval.count() > 0 &&
        std::chrono::steady_clock::now() >= node.next_sync) {
      node.next_sync = std::chrono::steady_clock::now() + options_.clock_sync_interval;
      SyncClock(node);
    }
  }
}

void HealthMonitor::SyncClock(Node& node) {
  auto log = Logger("controller.clock");
  std::vector<timing::SyncSample> burst;
  v1::SyncResponse last;
  std::string error;
  for (int i = 0; i < options_.clock_sync_burst; ++i) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) return;
    }
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + options_.timeout);
    v1::SyncRequest request;
    v1::SyncResponse response;
    const int64_t t1 = UnixNowNs();
    request.set_t1_ns(t1);
    grpc::Status rpc = node.clock->Sync(&context, request, &response);
    const int64_t t4 = UnixNowNs();
    if (!rpc.ok()) {
      error = absl::StrCat("NodeClock.Sync failed: ", rpc.error_message());
      break;
    }
    burst.push_back({t1, response.t2_ns(), response.t3_ns(), t4});
    last = std::move(response);
  }
  const bool accepted = node.estimator.AddBurst(burst);
  const timing::ClockEstimate e = node.estimator.Current();

  std::lock_guard<std::mutex> lock(mutex_);
  v1::ClockStatus& c = *node.status.mutable_clock();
  const bool was_flagged = c.flagged();
  const bool was_measured = c.measured();
  c.set_error(error);
  if (!burst.empty() && last.has_ptp()) *c.mutable_ptp() = last.ptp();
  if (burst.empty()) {
    // No exchange at all: the old estimate is not trusted any longer.
    c.set_measured(false);
  } else if (e.valid) {
    c.set_measured(true);
    c.set_estimate_at_unix_ns(e.at_ns);
    c.set_offset_ns(e.offset_ns);
    c.set_uncertainty_ns(e.uncertainty_ns);
    c.set_drift_ppm(e.drift_ppm);
    c.set_drift_known(e.drift_known);
    c.set_min_rtt_ns(e.min_delay_ns);
    c.set_samples(e.samples);
    if (accepted) c.set_last_sync_unix_ns(UnixNowNs());
  }
  if (!c.measured()) {
    c.set_flagged(node.target.clock_required);
  } else {
    c.set_flagged(c.limit_ns() > 0 && c.uncertainty_ns() > c.limit_ns());
  }
  if (!was_flagged && c.flagged() && !c.measured()) {
    log->warn("{}: clock not measured ({}); its scheduled software triggers need it", node.target.id,
              error.empty() ? "no exchange kept" : error);
  } else if (!was_flagged && c.flagged()) {
    log->warn("{}: clock uncertainty {:.1f} us exceeds the {:.1f} us its trigger mode tolerates ({})", node.target.id,
              c.uncertainty_ns() / 1e3, c.limit_ns() / 1e3, c.limit_reason());
  } else if (was_flagged && !c.flagged()) {
    log->info("{}: clock uncertainty {:.1f} us is within {:.1f} us again", node.target.id, c.uncertainty_ns() / 1e3,
              c.limit_ns() / 1e3);
  }
  if (was_flagged != c.flagged() || was_measured != c.measured()) {
    ++generation_;
    changed_.notify_all();
  }
}

}  // namespace stage::controller
