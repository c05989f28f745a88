// Capturing takes: see capture.h.
#include "capture.h"

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/clock.h"
#include "stage/common/file_util.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/proto_json.h"
#include "stage/common/status.h"
#include "stage/common/take_names.h"
#include "stage/common/version.h"
#include "stage/storage/frame_file.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"
#include "stage/timing/waveform.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "stage/v1/sim.grpc.pb.h"
#include "take_watch.h"

namespace stage::controller {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

// Armed light nodes go dark after this long without the controller's heartbeat, which comes every kLightHeartbeatMs.
constexpr uint32_t kLightHeartbeatTimeoutMs = 1000;
constexpr int kLightHeartbeatMs = 200;

void Deadline(grpc::ClientContext* c, int ms) {
  c->set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(ms));
}

// Calls `rpc` with a fresh context and a deadline of `deadline_ms` a try until the node answers, fails for another
// reason than its deadline (it is gone, or refuses), or `give_up` has passed. For requests a node answers the same when
// asked twice (arming a take, its plan, disarming): a node slow to answer on a loaded host is asked again rather than
// counted out.
grpc::Status Patiently(int deadline_ms, Clock::time_point give_up,
                       const std::function<grpc::Status(grpc::ClientContext*)>& rpc) {
  while (true) {
    grpc::ClientContext context;
    Deadline(&context, deadline_ms);
    grpc::Status s = rpc(&context);
    if (s.error_code() != grpc::StatusCode::DEADLINE_EXCEEDED || Clock::now() >= give_up) return s;
  }
}

// take.json: what the take was and how it ended (docs/storage.md).
absl::Status WriteTakeJson(const std::string& dir, const v1::RigConfig& rig, const v1::Schedule& schedule,
                           const v1::TakeSummary& summary, v1::TakeState state) {
  std::string text = absl::StrCat(
      "{\n\"format\": \"fastage-take-1\",\n\"software\": \"FaStage ", kVersion, "\",\n\"state\": \"",
      storage::TakeStateText(state), "\",\n\"schedule_hash\": \"", schedule.hash(), "\",\n\"rig_hash\": \"",
      schedule.rig_hash(), "\",\n\"summary\": ", ToContractJson(summary), ",\n\"rig\": ", ToContractJson(rig), "\n}\n");
  return WriteFileAtomically(dir + "/take.json", text);  // a reader sees the old file or the new one
}

// Adds one loss of `reason` to `counts` (its reasons in the enum's order, each once).
void AddLoss(v1::LedgerCounts* counts, storage::LossReason reason, int64_t n = 1) {
  const v1::LossReason r = storage::ToProto(reason);
  for (v1::LossCount& l : *counts->mutable_lost()) {
    if (l.reason() == r) {
      l.set_frames(l.frames() + n);
      return;
    }
  }
  v1::LossCount* l = counts->add_lost();
  l->set_reason(r);
  l->set_frames(n);
  std::sort(counts->mutable_lost()->begin(), counts->mutable_lost()->end(),
            [](const v1::LossCount& a, const v1::LossCount& b) { return a.reason() < b.reason(); });
}

// The progress entry of `role`, made on first use (in the order the roles come).
v1::RoleProgress* RoleOf(v1::CaptureProgress* progress, v1::CameraRole role) {
  for (v1::RoleProgress& r : *progress->mutable_roles()) {
    if (r.role() == role) return &r;
  }
  v1::RoleProgress* r = progress->add_roles();
  r->set_role(role);
  return r;
}

void Add(v1::LedgerCounts* c, storage::LossReason reason) {
  c->set_expected(c->expected() + 1);
  if (reason == storage::LossReason::kNone) {
    c->set_stored(c->stored() + 1);
  } else {
    AddLoss(c, reason);
  }
}

// The sync generator (the simulated world's bus): plans a run, or starts exactly the one planned.
absl::StatusOr<v1::WorldRunReply> RunWorld(v1::SimWorld::Stub& world, const v1::RunWorldRequest& request,
                                           Clock::time_point give_up) {
  v1::WorldRunReply run;
  // Planning is a question, and starting the run planned twice starts it once: a world slow to answer is asked again.
  grpc::Status s =
      Patiently(5000, give_up, [&](grpc::ClientContext* context) { return world.Run(context, request, &run); });
  if (!s.ok()) return FromGrpcStatus(s);
  return run;
}

// Ends the world's run at the next multiple of `align` slots: the run's end slot on the bus. `what` heads the error.
absl::StatusOr<int64_t> EndWorldRun(v1::SimWorld::Stub& world, int64_t align, const std::string& what) {
  v1::EndRunRequest end;
  end.set_align_slots(align);
  grpc::ClientContext context;
  Deadline(&context, 5000);
  v1::WorldRunReply run;
  grpc::Status s = world.EndRun(&context, end, &run);
  if (!s.ok()) return absl::FailedPreconditionError(absl::StrCat(what, ": ", s.error_message()));
  return run.end_slot();
}

using Gaps = std::vector<std::pair<int64_t, int64_t>>;

bool InGap(const Gaps& gaps, int64_t slot) {
  for (const auto& [first, end] : gaps) {
    if (slot >= first && slot < end) return true;
  }
  return false;
}

// The slots a camera fires in over a take of `slots` slots, with those in its gaps (pauses) apart.
void CameraSlots(const v1::CameraTiming& timing, int64_t slots, const Gaps& gaps, std::vector<int64_t>* expected,
                 std::vector<int64_t>* paused) {
  const int64_t d = std::max<uint32_t>(1, timing.divider());
  for (int64_t k = timing.slot_phase(); k < slots; k += d) (InGap(gaps, k) ? paused : expected)->push_back(k);
}

int64_t ExpectedFrames(const v1::CameraTiming& timing, int64_t slots, const Gaps& gaps) {
  int64_t n = timing::FiringsInTake(timing, slots);
  const int64_t d = std::max<uint32_t>(1, timing.divider()), p = timing.slot_phase();
  auto before = [&](int64_t s) { return s > p ? (s - p - 1) / d + 1 : 0; };  // firings in [0, s)
  for (const auto& [first, end] : gaps) n -= before(std::min(end, slots)) - before(std::min(first, slots));
  return n;
}

}  // namespace

struct Capturer::Take {
  struct Cam {
    const v1::CameraConfig* config;
    const v1::CameraTiming* timing;
    std::unique_ptr<v1::CameraNode::Stub> stub;
    std::string path;  // its frame file
    bool armed = false;
    std::string error;
    Clock::time_point next_preview;
    std::optional<Clock::time_point> refused_since;  // its node has refused every poll since
  };
  std::string id, dir;
  storage::TakeRow row;
  v1::TakeSummary summary;
  int64_t cycle = 38;
  int64_t capture_slots = 0;  // asked for: frames x cycle
  std::unique_ptr<v1::SimWorld::Stub> world;
  std::vector<std::unique_ptr<v1::LightNode::Stub>> lights;
  std::vector<Cam> cams;
  std::vector<std::string> not_ready;
  bool ran = false;
  // Guarded by the Capturer's mutex_ once the take runs (Pause, Resume and Abort change them):
  int64_t first_bus = 0;  // the take's slot 0 on the bus
  int64_t slots = 0;      // its length so far, gaps included
  int64_t run_first = 0;  // the current (or last) run, in slots of the take
  int64_t run_end = 0;
  int64_t done_slots = 0;  // slots captured in the runs before the current one
  Gaps paused;
  Clock::time_point paused_since;
  bool aborted = false;
  bool ground_truth = true;
  // A pause, resume or abort is changing the take's plan (set with its new slots, cleared once the session's state
  // says so): the watch holds the take meanwhile. And the watch has ended: the take is finishing; a pause or abort
  // comes too late.
  bool plan_changing = false;
  bool watch_ended = false;
  Clock::time_point armed_at = Clock::now();
  // Why the take was given up before every frame came, if it was (nothing moved for the stall limit).
  std::string stalled;
  // The lights' heartbeat (ArmLightRequest.heartbeat_timeout_ms) from arming to disarming, a thread per light node,
  // and what the nodes report of the take on the way: their take_faults, by light node index.
  std::vector<std::thread> heartbeats;
  std::mutex heartbeat_mutex;
  std::condition_variable heartbeat_wake;
  bool heartbeat_stop = false;                           // guarded by heartbeat_mutex
  std::map<int, std::vector<std::string>> light_faults;  // guarded by heartbeat_mutex

  void StopHeartbeat() {
    {
      std::lock_guard<std::mutex> lock(heartbeat_mutex);
      heartbeat_stop = true;
    }
    heartbeat_wake.notify_all();
    for (std::thread& t : heartbeats) t.join();
    heartbeats.clear();
  }
  ~Take() { StopHeartbeat(); }
};

absl::StatusOr<std::unique_ptr<Capturer>> Capturer::Create(LoadedRig rig, v1::Schedule schedule, int timing_errors,
                                                           CaptureOptions options) {
  std::unique_ptr<Capturer> c(new Capturer());
  c->rig_ = std::move(rig);
  c->schedule_ = std::move(schedule);
  c->timing_errors_ = timing_errors;
  c->options_ = std::move(options);
  auto catalog = storage::Catalog::Open(c->options_.take_root);
  if (!catalog.ok()) return catalog.status();
  c->catalog_ = std::move(*catalog);
  auto patterns = timing::LoadRigPatternSet(c->rig_.rig, c->rig_.base_dir);
  if (patterns.ok()) {
    auto signature = timing::PatternSignature(*patterns);
    if (signature.ok()) {
      c->signature_ = *signature;
      c->have_signature_ = true;
    } else {
      Logger("controller")->warn("no alignment self-test for this pattern set: {}", signature.status().message());
    }
  }
  return c;
}

Capturer::~Capturer() = default;

v1::SessionState Capturer::state() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return state_;
}

std::string Capturer::current_take_id() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return current_take_;
}

void Capturer::SetState(v1::SessionState state) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ == state) return;
    Logger("controller")->info("session: {} -> {}", SessionStateName(state_), SessionStateName(state));
    state_ = state;
    // The session holds a take from its configuring to its end.
    if (state == v1::SESSION_STATE_CONFIGURING) current_take_ = events_.take_id();
    if (state == v1::SESSION_STATE_IDLE || state == v1::SESSION_STATE_ERROR) current_take_.clear();
  }
  if (options_.on_state_change) options_.on_state_change();
  v1::CaptureEvent e;
  e.set_state(state);
  events_.Emit(e);
}

void Capturer::Say(const std::string& message, bool warn) {
  if (warn) {
    Logger("controller")->warn("{}", message);
  } else {
    Logger("controller")->info("{}", message);
  }
  v1::CaptureEvent e;
  e.set_message(message);
  events_.Emit(e);
}

absl::StatusOr<v1::Preview> Capturer::GetPreview(const std::string& camera_id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = previews_.find(camera_id);
  if (it != previews_.end()) return it->second;
  for (const auto& c : rig_.rig.cameras()) {
    if (c.id() == camera_id) return absl::NotFoundError(absl::StrCat("camera \"", camera_id, "\": no preview yet"));
  }
  return absl::NotFoundError(absl::StrCat("\"", camera_id, "\" is no camera of the rig"));
}

absl::StatusOr<std::unique_ptr<Capturer::Take>> Capturer::ArmTake(const v1::CaptureRequest& request) {
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  const int64_t cycle = schedule_.patterns_size();
  if (request.frames() != 0 && request.seconds() != 0) {
    return absl::InvalidArgumentError(absl::StrCat("capture: give frames or seconds, not both (frames ",
                                                   request.frames(), ", seconds ", request.seconds(), ")"));
  }
  int64_t frames = request.frames();
  if (frames <= 0 && request.seconds() > 0) {
    frames =
        static_cast<int64_t>(std::ceil(request.seconds() * base.slot_rate_hz() / static_cast<double>(cycle) - 1e-9));
  }
  if (frames <= 0 || request.frames() < 0 || request.seconds() < 0) {
    return absl::InvalidArgumentError("capture: give a number of frames or seconds above 0");
  }
  if (timing_errors_ > 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("the rig's schedule has ", timing_errors_, " error(s): `stagectl timing check` shows them"));
  }
  if (std::string why; options_.estop != nullptr && options_.estop->latched(&why)) {
    return absl::FailedPreconditionError(
        absl::StrCat("the emergency stop is latched (", why, "): nothing arms until `stagectl estop --reset`"));
  }
  if (options_.world_address.empty()) {
    return absl::FailedPreconditionError(
        "no sync generator: the controller drives the simulated world's bus (stage-sim); a hardware slot clock comes "
        "with the light-node work");
  }
  auto say = [&](const std::string& m) { Say(m); };
  auto take = std::make_unique<Take>();
  take->cycle = cycle;
  take->ground_truth = !request.skip_ground_truth();
  take->capture_slots = frames * cycle;
  take->slots = take->capture_slots;
  take->run_end = take->slots;
  const int64_t now_unix = RealClock(RealClock::Kind::kRealtime).NowNs();
  STAGE_ASSIGN_OR_RETURN(take->id, catalog_->NextTakeId(rig_.rig.stage().id(), now_unix));
  // From here on every event names the take, the first (its configuring state) included.
  events_.Begin(take->id);
  SetState(v1::SESSION_STATE_CONFIGURING);
  struct BackToIdle {  // unless armed
    Capturer* c;
    bool armed = false;
    ~BackToIdle() {
      if (!armed) c->SetState(v1::SESSION_STATE_IDLE);
    }
  } back{this};

  take->dir = (fs::path(options_.take_root) / take->id).string();
  std::error_code ec;
  fs::create_directories(take->dir + "/cameras", ec);
  if (ec) return absl::UnavailableError(absl::StrCat(take->dir, ": ", ec.message()));
  storage::TakeRow& row = take->row;
  row.id = take->id;
  row.name = request.name();
  row.state = v1::TAKE_STATE_CONFIGURING;
  row.created_unix_ns = now_unix;
  row.slots = take->slots;
  row.duration_s = static_cast<double>(take->slots) / base.slot_rate_hz();
  row.rig_hash = schedule_.rig_hash();
  row.schedule_hash = schedule_.hash();
  row.dir = take->id;
  STAGE_RETURN_IF_ERROR(catalog_->CreateTake(row));
  v1::TakeSummary& summary = take->summary;
  summary.set_take_id(take->id);
  summary.set_name(request.name());
  summary.set_dir(take->dir);
  summary.set_frames(frames);
  summary.set_slots(take->slots);
  STAGE_RETURN_IF_ERROR(WriteTakeJson(take->dir, rig_.rig, schedule_, summary, v1::TAKE_STATE_CONFIGURING));
  {
    // The schedule as compiled, and as waveforms a logic-analyser viewer opens (the take's first 10 s at most).
    if (absl::Status s = WriteFileAtomically(take->dir + "/schedule.json", ToContractJson(schedule_)); !s.ok())
      say(std::string(s.message()));
    auto vcd = timing::ScheduleToVcd(schedule_, {0, std::min<int64_t>(take->slots, 10 * base.slot_rate_hz())});
    const absl::Status written = vcd.ok() ? WriteFileAtomically(take->dir + "/schedule.vcd", *vcd) : vcd.status();
    if (!written.ok()) say(absl::StrCat("schedule.vcd not written: ", written.message()));
  }
  say(absl::StrCat("take ", take->id, ": ", frames, " frames (", take->slots, " slots, ", row.duration_s, " s) into ",
                   take->dir));
  take->world = v1::SimWorld::NewStub(grpc::CreateChannel(options_.world_address, grpc::InsecureChannelCredentials()));

  // Arm: every light node its table, every camera node its plan (T0 comes when the take starts); the message names
  // who is not ready.
  for (int i = 0; i < rig_.rig.light_nodes_size() && i < schedule_.light_nodes_size(); ++i) {
    const auto& node = rig_.rig.light_nodes(i);
    take->lights.push_back(
        v1::LightNode::NewStub(grpc::CreateChannel(node.address(), grpc::InsecureChannelCredentials())));
    v1::ArmLightRequest arm;
    arm.set_take_id(take->id);
    *arm.mutable_table() = schedule_.light_nodes(i).table();
    arm.set_take_slots(take->slots);
    arm.set_heartbeat_timeout_ms(kLightHeartbeatTimeoutMs);
    v1::LightStats stats;
    grpc::Status s = Patiently(options_.arm_timeout_ms, StallDeadline(), [&](grpc::ClientContext* context) {
      return take->lights.back()->Arm(context, arm, &stats);
    });
    if (!s.ok()) take->not_ready.push_back(absl::StrCat(node.id(), " (", s.error_message(), ")"));
  }
  // The heartbeat: armed light nodes go dark when it stops (the controller died or lost them). One thread per node,
  // so that a node that hangs delays no other's. Its replies carry what the node saw of the take so far.
  for (size_t i = 0; i < take->lights.size(); ++i) {
    take->heartbeats.emplace_back([t = take.get(), i] {
      std::unique_lock<std::mutex> lock(t->heartbeat_mutex);
      while (!t->heartbeat_wake.wait_for(lock, std::chrono::milliseconds(kLightHeartbeatMs),
                                         [t] { return t->heartbeat_stop; })) {
        lock.unlock();
        v1::HeartbeatRequest beat;
        beat.set_take_id(t->id);
        grpc::ClientContext context;
        Deadline(&context, kLightHeartbeatMs);
        v1::LightStats stats;
        const bool heard = t->lights[i]->Heartbeat(&context, beat, &stats).ok() && stats.take_faults_size() > 0;
        lock.lock();
        if (heard) t->light_faults[static_cast<int>(i)].assign(stats.take_faults().begin(), stats.take_faults().end());
      }
    });
  }
  for (int i = 0; i < rig_.rig.cameras_size() && i < schedule_.cameras_size(); ++i) {
    Take::Cam c{&rig_.rig.cameras(i), &schedule_.cameras(i),
                v1::CameraNode::NewStub(
                    grpc::CreateChannel(rig_.rig.cameras(i).address(), grpc::InsecureChannelCredentials()))};
    c.path = absl::StrCat(take->dir, "/cameras/", c.config->id(), ".h5");
    v1::ArmCameraRequest arm;
    arm.set_take_id(take->id);
    arm.set_take_dir(take->dir);
    arm.set_start_later(true);
    arm.set_slot_rate_hz(base.slot_rate_hz());
    arm.set_slot_count(take->slots);
    arm.set_patterns_per_cycle(static_cast<uint32_t>(cycle));
    arm.mutable_trigger_plan()->set_source(c.timing->source());
    arm.mutable_trigger_plan()->set_divider(std::max<uint32_t>(1, c.timing->divider()));
    arm.mutable_trigger_plan()->set_slot_phase(c.timing->slot_phase());
    arm.set_trigger_delay_ns(base.TicksToNs(c.timing->trigger_ticks()));
    arm.set_preview_pattern(have_signature_ ? signature_.cross_full : 0);
    *arm.mutable_camera() = *c.config;
    *arm.mutable_patterns() = schedule_.patterns();
    const bool hs = c.config->role() == v1::CAMERA_ROLE_HIGH_SPEED;
    arm.set_burst(hs);
    if (hs) arm.set_burst_bytes(static_cast<uint64_t>(c.config->ram_gib() * (1ull << 30)));
    v1::ArmCameraResponse armed;
    grpc::Status s = Patiently(options_.arm_timeout_ms, StallDeadline(),
                               [&](grpc::ClientContext* context) { return c.stub->Arm(context, arm, &armed); });
    if (s.ok()) {
      c.armed = true;
      if (!armed.path().empty()) c.path = armed.path();
    } else {
      c.error = s.error_message();
      take->not_ready.push_back(absl::StrCat(c.config->id(), " (", s.error_message(), ")"));
    }
    take->cams.push_back(std::move(c));
  }
  if (!take->not_ready.empty()) say(absl::StrCat("not ready: ", absl::StrJoin(take->not_ready, ", ")));
  back.armed = true;
  SetState(v1::SESSION_STATE_ARMED);
  return take;
}

void Capturer::UpdateCameras(Take& take, bool with_t0) {
  v1::UpdateTakeRequest update;
  update.set_take_id(take.id);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (with_t0) {
      update.set_t0_bus_ns(take.summary.t0_bus_ns());
    }
    update.set_slot_count(take.slots);
    for (const auto& [first, end] : take.paused) {
      v1::SlotRange* r = update.add_paused();
      r->set_first(first);
      r->set_end(end);
    }
  }
  for (Take::Cam& c : take.cams) {
    if (!c.armed) continue;
    v1::ArmCameraResponse reply;
    grpc::Status s = Patiently(options_.arm_timeout_ms, StallDeadline(), [&](grpc::ClientContext* context) {
      return c.stub->UpdateTake(context, update, &reply);
    });
    if (!s.ok()) {
      // It keeps what it recorded; its report is checked against the take's plan at the end.
      Say(absl::StrCat(c.config->id(), " did not take the new plan: ", s.error_message()), /*warn=*/true);
    }
  }
}

bool Capturer::StartTake(Take& take) {
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  // The run of the bus the take will be, planned first so that every camera knows its T0 before it starts.
  v1::RunWorldRequest plan;
  plan.set_slots(take.capture_slots);
  plan.set_lead_slots(base.slot_rate_hz() / 2);  // real time: half a second to tell every node
  plan.set_align_slots(take.cycle);
  plan.set_plan_only(true);
  auto run = RunWorld(*take.world, plan, StallDeadline());
  if (!run.ok()) {
    Say(absl::StrCat("the sync generator (the simulated world at ", options_.world_address,
                     ") cannot plan the take: ", run.status().message()),
        /*warn=*/true);
    return false;
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    take.first_bus = run->first_slot();
    take.summary.set_t0_bus_ns(run->first_edge_ns());
  }
  UpdateCameras(take, /*with_t0=*/true);
  v1::RunWorldRequest start = plan;
  start.set_plan_only(false);
  start.set_first_slot(run->first_slot());
  if (auto started = RunWorld(*take.world, start, StallDeadline()); !started.ok()) {
    Say(absl::StrCat("the sync generator did not start: ", started.status().message()), /*warn=*/true);
    return false;
  }
  const int64_t now_unix = RealClock(RealClock::Kind::kRealtime).NowNs();
  take.row.t0_unix_ns = now_unix;
  take.summary.set_t0_unix_ns(now_unix);
  take.ran = true;
  SetState(v1::SESSION_STATE_CAPTURING);
  return true;
}

void Capturer::WatchTake(Take& take) {
  // Every camera's frames for the take, until all are in (and no pause holds the take), or nothing more can come (the
  // slot clock has produced every edge and no camera owes a frame), or nothing at all has moved for the stall limit.
  // A slow machine only makes this longer: devices that work on the take say so (take_watch.h).
  const auto start = Clock::now();
  TakeWatchOptions watch_options;
  watch_options.drain = std::chrono::milliseconds(options_.drain_ms);
  watch_options.stall = std::chrono::seconds(rig_.rig.controller().take_stall_s());
  TakeWatch watch(watch_options, start);
  while (true) {
    int64_t slots;
    Gaps gaps;
    v1::SessionState state;
    bool aborted;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      slots = take.slots;
      gaps = take.paused;
      state = state_;
      aborted = take.aborted;
    }
    v1::CaptureProgress progress;
    progress.set_phase(state == v1::SESSION_STATE_PAUSED     ? v1::CAPTURE_PHASE_PAUSED
                       : state == v1::SESSION_STATE_ABORTING ? v1::CAPTURE_PHASE_ABORTING
                                                             : v1::CAPTURE_PHASE_CAPTURING);
    TakeSnapshot snapshot;
    const auto now = Clock::now();
    for (Take::Cam& c : take.cams) {
      v1::RoleProgress* role = RoleOf(&progress, c.config->role());
      // What the take has so far (its end moves with a pause, a resume, an abort), and, shown, what it will have.
      const int64_t expected = ExpectedFrames(*c.timing, slots, gaps);
      const int64_t shown = aborted ? expected : ExpectedFrames(*c.timing, take.capture_slots, {});
      role->set_expected(role->expected() + shown);
      progress.set_frames_expected(progress.frames_expected() + shown);
      if (!c.armed) continue;
      TakeSnapshot::Camera& seen = snapshot.cameras.emplace_back();
      seen.id = c.config->id();
      seen.expected = expected;
      grpc::ClientContext context;
      Deadline(&context, 1000);
      v1::CameraStats stats;
      const grpc::Status polled = c.stub->GetStats(&context, v1::GetStatsRequest(), &stats);
      // Gone: refused for the drain (a reconnect refuses for a moment too), or answering without the take (it was
      // restarted): it delivers nothing more. Slow to answer: as it last said.
      if (polled.error_code() == grpc::StatusCode::UNAVAILABLE) {
        if (!c.refused_since) c.refused_since = now;
        seen.down = now - *c.refused_since >= std::chrono::milliseconds(options_.drain_ms);
      } else {
        c.refused_since.reset();
      }
      if (polled.ok() && stats.take_id() != take.id) seen.down = true;
      if (!polled.ok() || stats.take_id() != take.id) continue;
      seen.answered = true;
      seen.received = stats.take_frames_received();
      seen.owed = stats.frames_owed();
      seen.work = stats.device_work();
      seen.activity = stats.device_activity();
      const int64_t got = std::min(stats.take_frames_received(), expected);
      role->set_received(role->received() + got);
      role->set_lost(role->lost() + stats.take_frames_lost());
      progress.set_frames_received(progress.frames_received() + got);
      progress.set_frames_written(progress.frames_written() + stats.take_frames_written());
      progress.set_frames_lost(progress.frames_lost() + stats.take_frames_lost());
      if (state == v1::SESSION_STATE_CAPTURING && now >= c.next_preview) {
        // The console's view: the camera's latest full-on frame, small.
        c.next_preview = now + std::chrono::milliseconds(options_.preview_interval_ms);
        grpc::ClientContext pc;
        Deadline(&pc, 1000);
        v1::GetPreviewRequest pr;
        pr.set_max_size(options_.preview_size);
        v1::Preview preview;
        if (c.stub->GetPreview(&pc, pr, &preview).ok()) {
          std::lock_guard<std::mutex> lock(mutex_);
          previews_[c.config->id()] = std::move(preview);
        }
      }
    }
    ReadClock(take, &snapshot);
    const TakeVerdict verdict = watch.Observe(snapshot, Clock::now());
    progress.set_frames_owed(watch.owed());
    progress.set_waiting_for(watch.waiting_for());
    progress.set_elapsed_s(std::chrono::duration<double>(Clock::now() - start).count());
    v1::CaptureEvent e;
    *e.mutable_progress() = progress;
    events_.Emit(e);
    {
      // Decided under the lock, so that a pause either comes before this (and holds the take) or finds it finishing.
      std::lock_guard<std::mutex> lock(mutex_);
      // A pause, a resume or an abort on its way (its plan set, its state not yet) holds the take as a pause does.
      const bool changed = take.slots != slots || take.paused != gaps || state_ != state;
      if (changed || take.plan_changing || state_ == v1::SESSION_STATE_PAUSED) {
        watch.Restart(Clock::now());
      } else if (verdict == TakeVerdict::kComplete) {
        take.watch_ended = true;
        break;
      } else if (verdict == TakeVerdict::kDrained) {
        Logger("controller")
            ->warn("take {}: the slot clock has ended and no camera owes a frame, {} short", take.id,
                   progress.frames_expected() - progress.frames_received());
        take.watch_ended = true;
        break;
      } else if (verdict == TakeVerdict::kStalled) {
        take.stalled =
            absl::StrCat("nothing moved for ", rig_.rig.controller().take_stall_s(), " s",
                         watch.waiting_for().empty() ? "" : absl::StrCat(" while waiting for ", watch.waiting_for()));
        Logger("controller")->warn("take {}: stalled: {}", take.id, take.stalled);
        take.watch_ended = true;
        break;
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(250));
  }
}

void Capturer::ReadClock(Take& take, TakeSnapshot* snapshot) {
  // The sync generator's run: how many of its edges it has produced (the simulated world's bus).
  grpc::ClientContext context;
  Deadline(&context, 1000);
  v1::WorldRunReply run;
  if (!take.world->GetRun(&context, v1::GetRunRequest(), &run).ok()) return;
  int64_t run_first;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    run_first = take.first_bus + take.run_first;
  }
  if (run.first_slot() != run_first) return;  // not this take's run (yet)
  snapshot->clock_run_slots = run.end_slot() - run.first_slot();
  snapshot->clock_edges = std::clamp<int64_t>(run.current_slot() - run.first_slot() + 1, 0, snapshot->clock_run_slots);
}

absl::StatusOr<v1::SessionReply> Capturer::Pause() {
  std::lock_guard<std::mutex> control(control_mutex_);
  Take* take;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ != v1::SESSION_STATE_CAPTURING || running_ == nullptr) {
      return absl::FailedPreconditionError(
          absl::StrCat("pause: the session is ", SessionStateName(state_), ", not capturing"));
    }
    take = running_;
  }
  STAGE_ASSIGN_OR_RETURN(const int64_t run_end,
                         EndWorldRun(*take->world, take->cycle,
                                     absl::StrCat("pause: take ", take->id, " cannot stop at a frame boundary")));
  v1::SessionReply reply;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const int64_t at = run_end - take->first_bus;
    if (take->watch_ended) {
      return absl::FailedPreconditionError(absl::StrCat("pause: take ", take->id, " has ended; it is finishing"));
    }
    if (at >= take->run_end) {
      return absl::FailedPreconditionError(
          absl::StrCat("pause: take ", take->id, " is in its last frame; it ends at slot ", take->run_end));
    }
    take->plan_changing = true;  // until the session says paused
    take->done_slots += at - take->run_first;
    take->run_end = at;
    take->slots = at;
    take->paused_since = Clock::now();
    reply.set_take_id(take->id);
    reply.set_slot(at);
    reply.set_message(absl::StrCat("take ", take->id, " pauses at slot ", at, " (frame ", at / take->cycle, ")"));
  }
  UpdateCameras(*take, /*with_t0=*/false);
  SetState(v1::SESSION_STATE_PAUSED);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    take->plan_changing = false;
  }
  reply.set_state(v1::SESSION_STATE_PAUSED);
  Logger("controller")->info("{}", reply.message());
  return reply;
}

absl::StatusOr<v1::SessionReply> Capturer::Resume() {
  std::lock_guard<std::mutex> control(control_mutex_);
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  Take* take;
  int64_t remaining, pause_at, min_gap;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ != v1::SESSION_STATE_PAUSED || running_ == nullptr) {
      return absl::FailedPreconditionError(
          absl::StrCat("resume: the session is ", SessionStateName(state_), ", not paused"));
    }
    take = running_;
    remaining = take->capture_slots - take->done_slots;
    pause_at = take->slots;
    // The gap is as long as the pause was (at least one frame), so that the take's slots stay the stage's time.
    const double paused_s = std::chrono::duration<double>(Clock::now() - take->paused_since).count();
    min_gap = std::max<int64_t>(take->cycle, static_cast<int64_t>(paused_s * base.slot_rate_hz()));
  }
  v1::RunWorldRequest plan;
  plan.set_slots(remaining);
  plan.set_lead_slots(base.slot_rate_hz() / 2);
  plan.set_align_slots(take->cycle);
  plan.set_min_first_slot(take->first_bus + pause_at + min_gap);
  plan.set_plan_only(true);
  auto run = RunWorld(*take->world, plan, StallDeadline());
  if (!run.ok()) return Annotate(run.status(), absl::StrCat("resume: take ", take->id, ": the sync generator"));
  const int64_t from = run->first_slot() - take->first_bus;
  int64_t run_first_before;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    take->plan_changing = true;  // until the session says capturing (or the resume fails)
    run_first_before = take->run_first;
    take->paused.emplace_back(pause_at, from);
    take->slots = from + remaining;
    take->run_first = from;
    take->run_end = take->slots;
  }
  UpdateCameras(*take, /*with_t0=*/false);
  v1::RunWorldRequest start = plan;
  start.set_plan_only(false);
  start.set_first_slot(run->first_slot());
  if (auto started = RunWorld(*take->world, start, StallDeadline()); !started.ok()) {
    // Still paused: the gap stays open until a resume that starts, or an abort.
    std::lock_guard<std::mutex> lock(mutex_);
    take->paused.pop_back();
    take->slots = pause_at;
    take->run_end = pause_at;
    take->run_first = run_first_before;
    take->plan_changing = false;
    return Annotate(started.status(), absl::StrCat("resume: take ", take->id, ": the sync generator"));
  }
  SetState(v1::SESSION_STATE_CAPTURING);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    take->plan_changing = false;
  }
  v1::SessionReply reply;
  reply.set_state(v1::SESSION_STATE_CAPTURING);
  reply.set_take_id(take->id);
  reply.set_slot(from);
  reply.set_message(absl::StrCat("take ", take->id, " resumes at slot ", from, " (frame ", from / take->cycle,
                                 "); slots ", pause_at, "-", from - 1, " are its gap"));
  Logger("controller")->info("{}", reply.message());
  return reply;
}

absl::StatusOr<v1::SessionReply> Capturer::Abort() {
  std::lock_guard<std::mutex> control(control_mutex_);
  std::unique_ptr<Take> armed;
  Take* take = nullptr;
  v1::SessionState was;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    was = state_;
    if (state_ == v1::SESSION_STATE_ARMED && armed_ != nullptr) {
      armed = std::move(armed_);
      armed->aborted = true;
    } else if ((state_ == v1::SESSION_STATE_CAPTURING || state_ == v1::SESSION_STATE_PAUSED) && running_ != nullptr) {
      take = running_;
    } else {
      return absl::FailedPreconditionError(absl::StrCat("abort: the session is ", SessionStateName(state_),
                                                        "; only an armed, capturing or paused take can be aborted"));
    }
  }
  v1::SessionReply reply;
  if (armed != nullptr) {
    // Nothing ran: the take ends here, with no frames.
    SetState(v1::SESSION_STATE_ABORTING);
    const std::string id = armed->id;
    auto summary = FinalizeTake(*armed);
    if (!summary.ok()) return summary.status();
    reply.set_state(state());
    reply.set_take_id(id);
    reply.set_message(absl::StrCat("take ", id, " aborted before it started"));
    return reply;
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (take->watch_ended) {
      return absl::FailedPreconditionError(absl::StrCat("abort: take ", take->id, " has ended; it is finishing"));
    }
    take->plan_changing = true;  // until the session says aborting
  }
  struct Settled {  // the plan is settled on every way out
    Capturer* c;
    Take* t;
    ~Settled() {
      std::lock_guard<std::mutex> lock(c->mutex_);
      t->plan_changing = false;
    }
  } settled{this, take};
  if (was == v1::SESSION_STATE_CAPTURING) {
    STAGE_ASSIGN_OR_RETURN(const int64_t run_end,
                           EndWorldRun(*take->world, 1, absl::StrCat("abort: take ", take->id, " cannot be stopped")));
    std::lock_guard<std::mutex> lock(mutex_);
    const int64_t at = run_end - take->first_bus;
    take->done_slots += std::min(at, take->run_end) - take->run_first;
    take->run_end = std::min(at, take->run_end);
    take->slots = take->run_end;
  }
  int64_t at;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    take->aborted = true;
    at = take->slots;
  }
  UpdateCameras(*take, /*with_t0=*/false);
  SetState(v1::SESSION_STATE_ABORTING);
  reply.set_state(v1::SESSION_STATE_ABORTING);
  reply.set_take_id(take->id);
  reply.set_slot(at);
  reply.set_message(absl::StrCat("take ", take->id, " aborted at slot ", at, "; what it recorded is kept"));
  Logger("controller")->info("{}", reply.message());
  return reply;
}

absl::StatusOr<v1::TakeSummary> Capturer::Arm(const v1::CaptureRequest& request, const CaptureEventFn& on_event) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ != v1::SESSION_STATE_IDLE && state_ != v1::SESSION_STATE_ERROR) {
      return absl::FailedPreconditionError(
          absl::StrCat("arm: the session is ", SessionStateName(state_), "; wait for it"));
    }
  }
  Following following(&events_, on_event);
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Take> take, ArmTake(request));
  v1::TakeSummary summary = take->summary;
  std::lock_guard<std::mutex> lock(mutex_);
  armed_ = std::move(take);
  return summary;
}

absl::StatusOr<v1::TakeSummary> Capturer::Capture(const v1::CaptureRequest& request, const CaptureEventFn& on_event) {
  std::unique_ptr<Take> take;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ == v1::SESSION_STATE_ARMED && armed_ != nullptr) {
      const int64_t frames = armed_->capture_slots / armed_->cycle;
      if (request.frames() > 0 && request.frames() != frames) {
        return absl::InvalidArgumentError(absl::StrCat("capture: take ", armed_->id, " is armed for ", frames,
                                                       " frames, not ", request.frames(),
                                                       "; capture it as armed, or abort it"));
      }
      take = std::move(armed_);
      running_ = take.get();
    } else if (state_ != v1::SESSION_STATE_IDLE && state_ != v1::SESSION_STATE_ERROR) {
      return absl::FailedPreconditionError(
          absl::StrCat("capture: the session is ", SessionStateName(state_), "; wait for it"));
    }
  }
  // The caller follows the take's events until it ends (or goes away: the take goes on).
  Following following(&events_, on_event);
  if (take == nullptr) {
    STAGE_ASSIGN_OR_RETURN(take, ArmTake(request));
    std::lock_guard<std::mutex> lock(mutex_);
    running_ = take.get();
  }
  return RunArmedTake(std::move(take));
}

absl::StatusOr<v1::TakeSummary> Capturer::RunArmedTake(std::unique_ptr<Take> take) {
  const bool abort_on_failure = rig_.rig.controller().node_failure_policy() == v1::NODE_FAILURE_POLICY_ABORT;
  bool any_camera = false;
  for (const Take::Cam& c : take->cams) any_camera = any_camera || c.armed;
  if (!any_camera) {
    Say("no camera is ready: the take does not run", /*warn=*/true);
  } else if (take->not_ready.empty() || !abort_on_failure) {
    if (StartTake(*take)) WatchTake(*take);
  }
  auto summary = FinalizeTake(*take);
  std::lock_guard<std::mutex> lock(mutex_);
  running_ = nullptr;
  return summary;
}

absl::StatusOr<v1::TakeSummary> Capturer::FinalizeTake(Take& take) {
  auto emit = [&](const v1::CaptureEvent& e) { events_.Emit(e); };
  auto say = [&](const std::string& m) { Say(m); };
  if (state() != v1::SESSION_STATE_ABORTING) SetState(v1::SESSION_STATE_FINALIZING);
  int64_t slots;
  Gaps gaps;
  bool aborted;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    slots = take.ran ? take.slots : 0;
    gaps = take.paused;
    aborted = take.aborted;
  }
  v1::TakeSummary& summary = take.summary;
  summary.set_slots(slots);
  summary.set_aborted(aborted);
  for (const auto& [first, end] : gaps) {
    v1::SlotRange* r = summary.add_paused();
    r->set_first(first);
    r->set_end(end);
  }

  // Every camera accounts for its slots, all at once (a burst offload takes its time).
  std::vector<v1::CameraTakeReport> reports(take.cams.size());
  std::vector<char> reported(take.cams.size(), 0);  // not vector<bool>: set from several threads
  {
    std::vector<std::thread> finishing;
    std::atomic<size_t> done{0};
    // Set (release) once a camera's Finish has returned: its report is then what it wrote.
    std::unique_ptr<std::atomic<bool>[]> finished(new std::atomic<bool>[take.cams.size()]);
    for (size_t i = 0; i < take.cams.size(); ++i) finished[i].store(false);
    for (size_t i = 0; i < take.cams.size(); ++i) {
      if (!take.cams[i].armed) continue;
      finishing.emplace_back([&, i] {
        Take::Cam& c = take.cams[i];
        v1::FinishCameraRequest finish;
        finish.set_take_id(take.id);
        finish.set_drain_ms(static_cast<uint32_t>(take.ran ? options_.drain_ms : 1));
        grpc::ClientContext context;
        Deadline(&context, options_.drain_ms + 600'000);
        grpc::Status s = c.stub->Finish(&context, finish, &reports[i]);
        if (s.ok()) {
          reported[i] = true;
        } else {
          c.error = s.error_message();
        }
        finished[i].store(true, std::memory_order_release);
        done.fetch_add(1);
      });
    }
    // Meanwhile: what the burst cameras have written of what they held (their offload after the take).
    int64_t to_write = 0;
    for (size_t i = 0; i < take.cams.size(); ++i) {
      if (take.cams[i].armed && take.cams[i].config->role() == v1::CAMERA_ROLE_HIGH_SPEED)
        to_write += ExpectedFrames(*take.cams[i].timing, slots, gaps);
    }
    while (done.load() < finishing.size()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(500));
      if (done.load() >= finishing.size() || to_write == 0) continue;
      v1::CaptureProgress progress;
      progress.set_phase(v1::CAPTURE_PHASE_OFFLOADING);
      progress.set_frames_expected(to_write);
      for (size_t i = 0; i < take.cams.size(); ++i) {
        Take::Cam& c = take.cams[i];
        if (!c.armed || c.config->role() != v1::CAMERA_ROLE_HIGH_SPEED) continue;
        if (finished[i].load(std::memory_order_acquire)) {
          progress.set_frames_written(progress.frames_written() + (reported[i] ? reports[i].frames_written() : 0));
          continue;
        }
        grpc::ClientContext context;
        Deadline(&context, 1000);
        v1::CameraStats stats;
        if (c.stub->GetStats(&context, v1::GetStatsRequest(), &stats).ok() && stats.take_id() == take.id) {
          progress.set_frames_written(progress.frames_written() + stats.take_frames_written());
        }
      }
      v1::CaptureEvent e;
      *e.mutable_progress() = progress;
      emit(e);
    }
    for (std::thread& t : finishing) t.join();
  }
  std::vector<storage::LedgerEntry> ledger;
  v1::LedgerCounts* total = summary.mutable_total();
  auto add = [&](v1::LedgerCounts* cs, storage::LedgerEntry e) {
    for (v1::LedgerCounts* c : {cs, total}) {
      if (e.reason == storage::LossReason::kPaused) {
        c->set_paused(c->paused() + 1);
      } else {
        Add(c, e.reason);
      }
    }
    ledger.push_back(std::move(e));
  };
  uint64_t bytes = 0;
  for (size_t i = 0; i < take.cams.size(); ++i) {
    Take::Cam& c = take.cams[i];
    const v1::CameraTakeReport& report = reports[i];
    v1::CameraTakeSummary* cs = summary.add_cameras();
    cs->set_camera_id(c.config->id());
    cs->set_role(c.config->role());
    std::vector<int64_t> expected, in_gaps;
    CameraSlots(*c.timing, slots, gaps, &expected, &in_gaps);
    for (int64_t k : in_gaps) {
      add(cs->mutable_counts(), {c.config->id(), k, static_cast<int32_t>(k % take.cycle), storage::LossReason::kPaused,
                                 std::nullopt, "the take was paused"});
    }
    // What the camera says of each slot; a node that cannot report leaves what its file holds.
    std::map<int64_t, storage::LedgerEntry> known;
    if (reported[i]) {
      cs->set_path(report.path());
      cs->set_bytes(report.bytes());
      cs->set_error(report.error());
      bytes += report.bytes();
      for (const v1::SlotRecord& r : report.slots()) {
        known[r.slot()] = {c.config->id(),
                           r.slot(),
                           r.pattern(),
                           static_cast<storage::LossReason>(r.reason()),
                           r.has_frame_id() ? std::optional<uint64_t>(r.frame_id()) : std::nullopt,
                           r.detail()};
      }
    } else if (take.ran) {
      cs->set_error(c.error.empty() ? "did not report" : c.error);
      auto file = storage::FrameFileReader::Open(c.path);
      auto records = file.ok() ? (*file)->Records() : absl::StatusOr<std::vector<storage::FrameRecord>>(file.status());
      if (records.ok()) {
        cs->set_path(c.path);
        // The writer died with space reserved ahead of its frames: give it back, so the file holds what it says.
        if (absl::Status s = storage::ReleaseReservedSpace(c.path); !s.ok()) say(std::string(s.message()));
        std::error_code ec;
        cs->set_bytes(fs::file_size(c.path, ec));
        bytes += cs->bytes();
        for (const storage::FrameRecord& r : *records) {
          if (r.status != storage::FrameStatus::kOk && r.status != storage::FrameStatus::kIncomplete) continue;
          known[r.slot] = {
              c.config->id(),
              r.slot,
              r.pattern,
              r.status == storage::FrameStatus::kOk ? storage::LossReason::kNone : storage::LossReason::kIncomplete,
              r.frame_id,
              "in the frame file the node left"};
        }
        say(absl::StrCat(c.config->id(), " did not report (", cs->error(), "): ", known.size(),
                         " frames recovered from ", c.path));
      }
    }
    const size_t first_entry = ledger.size();
    for (int64_t k : expected) {
      auto it = known.find(k);
      if (it != known.end() && it->second.reason != storage::LossReason::kPaused) {
        add(cs->mutable_counts(), it->second);
      } else {
        add(cs->mutable_counts(),
            {c.config->id(), k, static_cast<int32_t>(k % take.cycle), storage::LossReason::kNodeDown, std::nullopt,
             reported[i] ? "not in the camera's report" : cs->error()});
      }
    }
    std::vector<int64_t> lost_by_pattern(static_cast<size_t>(take.cycle), 0);
    for (size_t j = first_entry; j < ledger.size(); ++j) {
      if (!ledger[j].stored()) ++lost_by_pattern[static_cast<size_t>(ledger[j].pattern) % lost_by_pattern.size()];
    }
    for (int64_t n : lost_by_pattern) cs->add_lost_by_pattern(n);
    if (reported[i] && c.config->role() == v1::CAMERA_ROLE_HIGH_SPEED && have_signature_ && take.ran) {
      std::map<int64_t, double> brightness;
      for (int j = 0; j < report.brightness_slots_size() && j < report.brightness_size(); ++j) {
        brightness[report.brightness_slots(j)] = report.brightness(j);
      }
      const timing::AlignmentReport a = timing::CheckAlignment(signature_, static_cast<int>(take.cycle), brightness);
      v1::AlignmentSummary* as = summary.add_alignment();
      as->set_camera_id(c.config->id());
      as->set_ok(a.ok);
      as->set_shift(a.shift);
      as->set_residual(a.residual);
      for (int64_t b : a.bad_cycles) as->add_bad_cycles(b);
      as->set_message(a.message);
    }
  }
  std::vector<std::string> light_hints;
  const std::vector<LightDisarmed> disarmed = DisarmLights(take);
  for (size_t i = 0; i < take.lights.size(); ++i) {
    const std::string& node_id = rig_.rig.light_nodes(static_cast<int>(i)).id();
    std::vector<std::string> faults;
    {
      std::lock_guard<std::mutex> lock(take.heartbeat_mutex);
      faults = take.light_faults[static_cast<int>(i)];
    }
    if (!disarmed[i].error.empty()) {
      say(absl::StrCat("light node ", node_id, " did not disarm: ", disarmed[i].error));
      faults.push_back(absl::StrCat("did not disarm: ", disarmed[i].error));
    } else if (disarmed[i].stats.take_faults_size() > 0) {
      faults.assign(disarmed[i].stats.take_faults().begin(), disarmed[i].stats.take_faults().end());
    }
    for (const std::string& f : faults) {
      say(absl::StrCat("light node ", node_id, ": ", f));
      light_hints.push_back(absl::StrCat(node_id, ": ", f));
    }
  }

  if (take.ran && take.ground_truth && slots > 0) {
    // The simulated world's truth of the take's frames (not its pauses'): what processing is judged against.
    const std::string dir = take.dir + "/ground_truth";
    std::vector<std::pair<int64_t, int64_t>> runs;  // take frames [first, end) that ran
    int64_t from = 0;
    for (const auto& [first, end] : gaps) {
      if (first > from) runs.emplace_back(from / take.cycle, (first + take.cycle - 1) / take.cycle);
      from = end;
    }
    if (slots > from) runs.emplace_back(from / take.cycle, (slots + take.cycle - 1) / take.cycle);
    int64_t frames = 0;
    for (const auto& [first, end] : runs) frames += end - first;
    say(absl::StrCat("writing the ground truth of ", frames, " frame(s) to ", dir));
    for (const auto& [first, end] : runs) {
      v1::GroundTruthRequest gt;
      gt.set_dir(dir);
      gt.set_name_offset(take.first_bus / take.cycle);
      gt.set_first_frame(take.first_bus / take.cycle + first);
      gt.set_frames(end - first);
      grpc::ClientContext context;
      Deadline(&context, 1'800'000);
      v1::GroundTruthReply written;
      grpc::Status s = take.world->WriteGroundTruth(&context, gt, &written);
      if (s.ok()) {
        summary.set_ground_truth_dir(dir);
      } else {
        if (s.error_code() != grpc::StatusCode::UNIMPLEMENTED)
          say(absl::StrCat("no ground truth: ", s.error_message()));
        summary.clear_ground_truth_dir();
        break;
      }
    }
  }

  // The verdict, and what to do about it.
  std::vector<std::string> hints;
  if (aborted) {
    hints.push_back(take.ran ? absl::StrCat("aborted by the operator at slot ", slots, " (",
                                            take.done_slots / take.cycle, " of ", take.capture_slots / take.cycle,
                                            " frames ran); what was recorded is kept")
                             : "aborted by the operator before it started");
  }
  if (!take.ran && !aborted) {
    hints.push_back(take.not_ready.empty() ? "the sync generator never ran"
                                           : absl::StrCat("not ready: ", absl::StrJoin(take.not_ready, ", ")));
  }
  if (!take.stalled.empty()) hints.push_back(absl::StrCat("the take stalled: ", take.stalled));
  bool aligned = true;
  for (const auto& a : summary.alignment()) {
    if (!a.ok()) {
      aligned = false;
      hints.push_back(absl::StrCat(a.camera_id(), ": ", a.message()));
    }
  }
  for (const auto& cs : summary.cameras()) {
    const int64_t lost = cs.counts().expected() - cs.counts().stored();
    if (lost <= 0) continue;
    std::vector<std::string> why;
    for (const v1::LossCount& l : cs.counts().lost()) {
      why.push_back(absl::StrCat(l.frames(), " ", LossReasonName(l.reason())));
    }
    hints.push_back(absl::StrCat(cs.camera_id(), " lost ", lost, " (", absl::StrJoin(why, ", "), ")"));
  }
  // A light node that faulted during the take (a board that stopped answering, over temperature): its frames may be
  // lit wrong even where they are all stored.
  hints.insert(hints.end(), light_hints.begin(), light_hints.end());
  v1::TakeOutcome outcome = v1::TAKE_OUTCOME_COMPLETE;
  if (!take.ran || aborted || total->stored() == 0) {
    outcome = v1::TAKE_OUTCOME_FAILED;
  } else if (total->stored() < total->expected() || !aligned || !light_hints.empty()) {
    outcome = v1::TAKE_OUTCOME_DEGRADED;
  }
  summary.set_outcome(outcome);
  summary.set_bytes(bytes);
  if (!hints.empty()) {
    if (hints.size() > 6) {
      const size_t more = hints.size() - 5;
      hints.resize(5);
      hints.push_back(absl::StrCat("and ", more, " more"));
    }
    summary.set_hint(absl::StrCat(outcome == v1::TAKE_OUTCOME_COMPLETE ? "" : "retake? ", absl::StrJoin(hints, "; ")));
  }
  storage::TakeRow& row = take.row;
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  row.state = aborted                                ? v1::TAKE_STATE_ABORTED
              : outcome == v1::TAKE_OUTCOME_COMPLETE ? v1::TAKE_STATE_COMPLETE
              : outcome == v1::TAKE_OUTCOME_DEGRADED ? v1::TAKE_STATE_DEGRADED
                                                     : v1::TAKE_STATE_FAILED;
  row.outcome = outcome;
  row.slots = slots;
  row.duration_s = static_cast<double>(slots) / base.slot_rate_hz();
  row.frames_expected = total->expected();
  row.frames_stored = total->stored();
  row.size_bytes = static_cast<int64_t>(bytes);
  absl::Status kept = catalog_->RecordLedger(take.id, ledger);
  if (kept.ok()) kept = catalog_->UpdateTake(row);
  if (kept.ok()) kept = WriteTakeJson(take.dir, rig_.rig, schedule_, summary, row.state);
  if (!kept.ok()) {
    // The take's records are incomplete: the operator must know before the next take.
    say(absl::StrCat("take ", take.id, ": its records could not be kept: ", kept.message()));
    SetState(v1::SESSION_STATE_ERROR);
    return kept;
  }
  {
    // The take's final counts, once, then its summary.
    v1::CaptureEvent done;
    v1::CaptureProgress* p = done.mutable_progress();
    p->set_phase(v1::CAPTURE_PHASE_DONE);
    p->set_frames_expected(total->expected());
    p->set_frames_received(total->stored());
    p->set_frames_lost(total->expected() - total->stored());
    for (size_t i = 0; i < take.cams.size(); ++i) {
      const v1::CameraTakeSummary& cs = summary.cameras(static_cast<int>(i));
      v1::RoleProgress* role = RoleOf(p, cs.role());
      role->set_expected(role->expected() + cs.counts().expected());
      role->set_received(role->received() + cs.counts().stored());
      role->set_lost(role->lost() + cs.counts().expected() - cs.counts().stored());
      if (reported[i]) p->set_frames_written(p->frames_written() + reports[i].frames_written());
    }
    p->set_elapsed_s(std::chrono::duration<double>(Clock::now() - take.armed_at).count());
    emit(done);
  }
  v1::CaptureEvent last;
  *last.mutable_summary() = summary;
  emit(last);
  Logger("controller")
      ->info("take {}: {} ({} of {} frames stored)", take.id, TakeOutcomeName(outcome), total->stored(),
             total->expected());
  SetState(v1::SESSION_STATE_IDLE);
  return summary;
}

Clock::time_point Capturer::StallDeadline() const {
  const uint32_t stall_s = rig_.rig.controller().take_stall_s();
  return stall_s == 0 ? Clock::time_point::max() : Clock::now() + std::chrono::seconds(stall_s);
}

std::vector<Capturer::LightDisarmed> Capturer::DisarmLights(Take& take) {
  // Every light node at once. One that is slow to answer (a loaded host, a stopped process) is asked again for as long
  // as it is there, up to the stall limit; one that is gone (its process is not there) is not. The heartbeat goes on
  // meanwhile, so that a slow node does not go dark for the controller's silence; it stops once every node has
  // answered.
  std::vector<LightDisarmed> out(take.lights.size());
  const auto give_up = StallDeadline();
  std::vector<std::thread> disarming;
  for (size_t i = 0; i < take.lights.size(); ++i) {
    disarming.emplace_back([&, i] {
      v1::DisarmLightRequest disarm;
      disarm.set_take_id(take.id);
      const grpc::Status s = Patiently(2000, give_up, [&](grpc::ClientContext* context) {
        return take.lights[i]->Disarm(context, disarm, &out[i].stats);
      });
      if (!s.ok()) out[i].error = s.error_message();
    });
  }
  for (std::thread& t : disarming) t.join();
  take.StopHeartbeat();
  return out;
}

absl::StatusOr<TakeEvents::Joined> Capturer::Follow(const std::string& take_id, CaptureEventFn fn) {
  // Under the session's lock: the take cannot change between the check and the subscription.
  std::lock_guard<std::mutex> lock(mutex_);
  if (current_take_.empty() || (!take_id.empty() && take_id != current_take_)) {
    return absl::NotFoundError(take_id.empty() ? "no take is running (the session is " + SessionStateName(state_) + ")"
                                               : absl::StrCat("take \"", take_id, "\" is not running"));
  }
  TakeEvents::Joined joined = events_.Subscribe(std::move(fn));
  if (joined.take_id != current_take_) {
    events_.Unsubscribe(joined.id);
    return absl::NotFoundError(absl::StrCat("take \"", current_take_, "\" is not running"));
  }
  return joined;
}

absl::StatusOr<v1::LedgerPage> Capturer::GetLedger(const v1::GetLedgerRequest& request) const {
  constexpr int kDefaultPage = 1000, kMaxPage = 10000;
  if (request.page_size() < 0 || request.page_size() > kMaxPage) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_size ", request.page_size(), " is not in 0..", kMaxPage, " (0: ", kDefaultPage, ")"));
  }
  int64_t offset = 0;
  if (!request.page_token().empty() && (!absl::SimpleAtoi(request.page_token(), &offset) || offset < 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_token \"", request.page_token(), "\" is not one this controller gave"));
  }
  std::string id = request.take_id();
  if (id == "latest") {
    STAGE_ASSIGN_OR_RETURN(std::vector<storage::TakeRow> rows, catalog_->ListTakes());
    if (rows.empty()) return absl::NotFoundError(absl::StrCat("no take yet in ", options_.take_root));
    id = rows.back().id;
  }
  STAGE_RETURN_IF_ERROR(catalog_->GetTake(id).status());
  const int64_t size = request.page_size() > 0 ? request.page_size() : kDefaultPage;
  STAGE_ASSIGN_OR_RETURN(storage::Catalog::LedgerPage rows,
                         catalog_->ReadLedgerPage(id, request.camera_id(), request.lost_only(), offset, size));
  v1::LedgerPage page;
  page.set_take_id(id);
  page.set_total(rows.total);
  for (const storage::LedgerEntry& e : rows.entries) {
    v1::LedgerEntry* out = page.add_entries();
    out->set_camera_id(e.camera_id);
    out->set_slot(e.slot);
    out->set_pattern(e.pattern);
    out->set_reason(storage::ToProto(e.reason));
    if (e.frame_id) out->set_frame_id(*e.frame_id);
    out->set_detail(e.detail);
  }
  if (offset + static_cast<int64_t>(rows.entries.size()) < rows.total) {
    page.set_next_page_token(absl::StrCat(offset + static_cast<int64_t>(rows.entries.size())));
  }
  return page;
}

absl::StatusOr<v1::TakeList> Capturer::ListTakes() const {
  STAGE_ASSIGN_OR_RETURN(std::vector<storage::TakeRow> rows, catalog_->ListTakes());
  v1::TakeList list;
  list.set_take_root(options_.take_root);
  for (const auto& r : rows) {
    v1::TakeRecord* t = list.add_takes();
    t->set_id(r.id);
    t->set_name(r.name);
    t->set_state(r.state);
    t->set_outcome(r.outcome);
    t->set_created_unix_ns(r.created_unix_ns);
    t->set_duration_s(r.duration_s);
    t->set_size_bytes(static_cast<uint64_t>(r.size_bytes));
    t->set_frames_expected(r.frames_expected);
    t->set_frames_stored(r.frames_stored);
    t->set_dir((fs::path(options_.take_root) / r.dir).string());
  }
  return list;
}

absl::StatusOr<v1::TakeSummary> Capturer::GetTake(const std::string& id) const {
  storage::TakeRow row;
  if (id == "latest") {
    // The newest take in the catalog (ListTakes is oldest first).
    STAGE_ASSIGN_OR_RETURN(std::vector<storage::TakeRow> rows, catalog_->ListTakes());
    if (rows.empty()) return absl::NotFoundError(absl::StrCat("no take yet in ", options_.take_root));
    row = rows.back();
  } else {
    STAGE_ASSIGN_OR_RETURN(row, catalog_->GetTake(id));
  }
  const std::string path = (fs::path(options_.take_root) / row.dir / "take.json").string();
  auto text = ReadFileToString(path);
  if (!text.ok()) return text.status();
  nlohmann::json take = nlohmann::json::parse(*text, nullptr, /*allow_exceptions=*/false);
  if (take.is_discarded() || !take.contains("summary")) {
    return absl::DataLossError(absl::StrCat(path, ": not a take file with a summary"));
  }
  v1::TakeSummary summary;
  if (absl::Status s = FromContractJson(take["summary"].dump(), &summary); !s.ok()) {
    return absl::DataLossError(absl::StrCat(path, ": ", s.message()));
  }
  return summary;
}

}  // namespace stage::controller
