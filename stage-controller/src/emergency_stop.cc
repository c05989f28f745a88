// The emergency stop.
#include "emergency_stop.h"

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/logging.h"
#include "stage/common/rpc_channel.h"
#include "stage/v1/light_node.grpc.pb.h"

namespace stage::controller {

using Clock = std::chrono::steady_clock;

EmergencyStop::EmergencyStop(const v1::RigConfig& rig) : rig_(rig) {
  for (const v1::LightNodeConfig& node : rig_.light_nodes()) {
    if (node.address().empty()) {
      channels_.push_back(nullptr);
      continue;
    }
    channels_.push_back(MakeChannel(node.address()));
    channels_.back()->GetState(/*try_to_connect=*/true);
  }
}

EmergencyStop::~EmergencyStop() = default;

bool EmergencyStop::latched(std::string* reason) const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (reason != nullptr) *reason = reason_;
  return latched_;
}

namespace {

// Calls `rpc` on every light node at once (a thread each), filling one LightBlackout per node, in rig order.
template <typename Rpc>
void OnEveryLightNode(const v1::RigConfig& rig, const std::vector<std::shared_ptr<grpc::Channel>>& channels,
                      Clock::time_point start, Rpc rpc, v1::EmergencyStopReply* reply) {
  std::vector<v1::LightBlackout> results(channels.size());
  std::vector<std::thread> threads;
  for (size_t i = 0; i < channels.size(); ++i) {
    threads.emplace_back([&, i] {
      grpc::Status s(grpc::StatusCode::FAILED_PRECONDITION, "the rig gives this light node no address");
      if (channels[i] != nullptr) {
        auto stub = v1::LightNode::NewStub(channels[i]);
        grpc::ClientContext context;
        context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
        v1::LightStats stats;
        s = rpc(*stub, context, stats);
      }
      v1::LightBlackout& r = results[i];
      r.set_node_id(rig.light_nodes(static_cast<int>(i)).id());
      r.set_dark(s.ok());
      if (!s.ok()) r.set_error(s.error_message());
      r.set_ms(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
    });
  }
  for (auto& t : threads) t.join();
  bool all = true;
  for (auto& r : results) {
    all = all && r.dark();
    *reply->add_nodes() = std::move(r);
  }
  reply->set_all_dark(all);
  reply->set_elapsed_ms(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
}

}  // namespace

v1::EmergencyStopReply EmergencyStop::Stop(const std::string& reason) {
  const Clock::time_point start = Clock::now();
  const std::string why = reason.empty() ? "emergency stop" : absl::StrCat("emergency stop: ", reason);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    latched_ = true;
    reason_ = why;
  }
  // Dark first, everything else after.
  v1::EmergencyStopReply reply;
  v1::BlackoutRequest request;
  request.set_reason(why);
  OnEveryLightNode(
      rig_, channels_, start,
      [&](v1::LightNode::Stub& stub, grpc::ClientContext& context, v1::LightStats& stats) {
        return stub.Blackout(&context, request, &stats);
      },
      &reply);
  reply.set_latched(true);
  for (const auto& n : reply.nodes()) {
    if (n.dark()) {
      Logger("controller")->warn("{}: {} dark after {:.2f} ms", why, n.node_id(), n.ms());
    } else {
      Logger("controller")->error("{}: {} NOT confirmed dark: {}", why, n.node_id(), n.error());
    }
  }
  return reply;
}

absl::StatusOr<v1::EmergencyStopReply> EmergencyStop::Reset() {
  v1::EmergencyStopReply reply;
  v1::ResetBlackoutRequest request;
  OnEveryLightNode(
      rig_, channels_, Clock::now(),
      [&](v1::LightNode::Stub& stub, grpc::ClientContext& context, v1::LightStats& stats) {
        return stub.ResetBlackout(&context, request, &stats);
      },
      &reply);
  std::vector<std::string> failed;
  for (const auto& n : reply.nodes()) {
    if (!n.dark()) failed.push_back(absl::StrCat(n.node_id(), " (", n.error(), ")"));
  }
  if (!failed.empty()) {
    return absl::FailedPreconditionError(absl::StrCat("the emergency stop stays latched: ", absl::StrJoin(failed, ", "),
                                                      " did not leave blackout"));
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    latched_ = false;
    reason_.clear();
  }
  Logger("controller")->info("emergency stop reset: every light node is out of blackout");
  reply.set_latched(false);
  return reply;
}

}  // namespace stage::controller
