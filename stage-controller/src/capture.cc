// Capturing takes: see capture.h.
#include "capture.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <functional>
#include <map>
#include <optional>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "controller_metrics.h"
#include "stage/common/clock.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/proto_json.h"
#include "stage/common/status.h"
#include "stage/common/take_names.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/time_base.h"
#include "stage/timing/waveform.h"
#include "take_watch.h"

namespace stage::controller {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

// Armed light nodes go dark after this long without the controller's heartbeat, which comes every kLightHeartbeatMs.
constexpr uint32_t kLightHeartbeatTimeoutMs = 1000;
constexpr int kLightHeartbeatMs = 200;

// A pause, resume or abort changing a take's plan: its plan_changing flag is cleared (under the session's lock) on
// every way out.
class PlanSettled {
 public:
  PlanSettled(std::mutex* mutex, bool* changing) : mutex_(mutex), changing_(changing) {}
  ~PlanSettled() {
    std::lock_guard<std::mutex> lock(*mutex_);
    *changing_ = false;
  }
  PlanSettled(const PlanSettled&) = delete;
  PlanSettled& operator=(const PlanSettled&) = delete;

 private:
  std::mutex* mutex_;
  bool* changing_;
};

}  // namespace

absl::Status CaptureOptions::Validate() const {
  if (take_root.empty() || !fs::path(take_root).is_absolute()) {
    return absl::InvalidArgumentError(absl::StrCat("capture: take_root \"", take_root, "\" is not an absolute path"));
  }
  if (drain_ms < 0) return absl::InvalidArgumentError(absl::StrCat("capture: drain_ms ", drain_ms, " is below 0"));
  if (preview_interval_ms <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("capture: preview_interval_ms ", preview_interval_ms, " is not above 0"));
  }
  if (preview_size == 0) return absl::InvalidArgumentError("capture: preview_size is 0");
  if (poll_interval_ms <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("capture: poll_interval_ms ", poll_interval_ms, " is not above 0"));
  }
  return absl::OkStatus();
}

struct Capturer::Take {
  struct Cam {
    const v1::CameraConfig* config;
    const v1::CameraTiming* timing;
    std::unique_ptr<CameraClient> client;
    std::string path;  // its frame file
    bool armed = false;
    std::string error;
    Clock::time_point next_preview;
    std::optional<Clock::time_point> refused_since;  // its node has refused every poll since
    bool lost = false;                               // seen gone during the take
  };
  std::string id, dir;
  storage::TakeRow row;
  v1::TakeSummary summary;
  int64_t cycle = 38;
  int64_t capture_slots = 0;  // asked for: frames x cycle
  std::vector<std::unique_ptr<LightClient>> lights;
  std::vector<bool> light_armed;  // by light: its Arm succeeded (a node not ready is not asked to start its table)
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
  std::string abort_reason;  // why it was aborted, when not by the operator
  v1::GroundTruthScope ground_truth = v1::GROUND_TRUTH_SCOPE_FULL;
  // A pause, resume or abort is changing the take's plan (set before the generator hears of it, cleared once the
  // session's state says so): the watch holds the take meanwhile, and does not take the run's new end for a lost
  // generator. And the watch has ended: the take is finishing; a pause or abort comes too late.
  bool plan_changing = false;
  bool watch_ended = false;
  Clock::time_point armed_at = Clock::now();
  // Why the take was given up before every frame came, if it was (nothing moved for the stall limit).
  std::string stalled;
  // The sync generator: the last edge it said it produced (bus slot, -1 none), since when it has not answered, and,
  // once it is lost (gone, or its run ended before the take's end on its own), why and the take slot where the clock
  // stopped: no slot from there on fired.
  int64_t clock_current = -1;
  std::optional<Clock::time_point> clock_unanswered_since;
  std::string clock_lost;
  int64_t clock_end = -1;
  // The lights' heartbeat (ArmLightRequest.heartbeat_timeout_ms) from arming to disarming, a thread per light node,
  // what the nodes report of the take on the way (their take_faults, by light node index), and since when a node has
  // refused the heartbeat (it is gone).
  std::vector<std::thread> heartbeats;
  std::mutex heartbeat_mutex;
  std::condition_variable heartbeat_wake;
  bool heartbeat_stop = false;                           // guarded by heartbeat_mutex
  std::map<int, std::vector<std::string>> light_faults;  // guarded by heartbeat_mutex
  std::map<int, Clock::time_point> light_refused_since;  // guarded by heartbeat_mutex

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
                                                           CaptureOptions options, CaptureDevices devices) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (!devices.nodes.camera || !devices.nodes.light) {
    return absl::InvalidArgumentError("capture: the node clients (camera and light) are not set");
  }
  std::unique_ptr<Capturer> c(new Capturer());
  c->rig_ = std::move(rig);
  c->schedule_ = std::move(schedule);
  c->timing_errors_ = timing_errors;
  c->options_ = std::move(options);
  c->devices_ = std::move(devices);
  STAGE_ASSIGN_OR_RETURN(c->records_, TakeRecords::Open(c->options_.take_root));
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
  c->session_metrics_ = CollectSessionState(c.get());
  return c;
}

Capturer::~Capturer() = default;

v1::SessionState Capturer::state() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return session_.state();
}

std::string Capturer::current_take_id() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return current_take_;
}

void Capturer::SetState(v1::SessionState state) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const v1::SessionState was = session_.state();
    absl::StatusOr<bool> changed = session_.Transition(state);
    if (!changed.ok()) {
      Logger("controller")->error("{} (a defect: please report it)", changed.status().message());
      return;
    }
    if (!*changed) return;
    Logger("controller")->info("session: {} -> {}", SessionStateName(was), SessionStateName(state));
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
  if (!v1::GroundTruthScope_IsValid(request.ground_truth())) {
    return absl::InvalidArgumentError(
        absl::StrCat("capture: ground_truth ", request.ground_truth(), " is not a GroundTruthScope"));
  }
  if (timing_errors_ > 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("the rig's schedule has ", timing_errors_, " error(s): `stagectl timing check` shows them"));
  }
  if (std::string why; options_.estop != nullptr && options_.estop->latched(&why)) {
    return absl::FailedPreconditionError(
        absl::StrCat("the emergency stop is latched (", why, "): nothing arms until `stagectl estop --reset`"));
  }
  if (devices_.generator == nullptr) {
    return absl::FailedPreconditionError(absl::StrCat(
        "no sync generator: ", devices_.no_generator.empty() ? "this controller has none" : devices_.no_generator));
  }
  auto say = [&](const std::string& m) { Say(m); };
  auto take = std::make_unique<Take>();
  take->cycle = cycle;
  take->ground_truth = request.ground_truth() == v1::GROUND_TRUTH_SCOPE_UNSPECIFIED ? v1::GROUND_TRUTH_SCOPE_FULL
                                                                                    : request.ground_truth();
  take->capture_slots = frames * cycle;
  take->slots = take->capture_slots;
  take->run_end = take->slots;
  const int64_t now_unix = RealClock(RealClock::Kind::kRealtime).NowNs();
  STAGE_ASSIGN_OR_RETURN(take->id, records_->NextTakeId(rig_.rig.stage().id(), now_unix));
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
  v1::TakeSummary& summary = take->summary;
  summary.set_take_id(take->id);
  summary.set_name(request.name());
  summary.set_dir(take->dir);
  summary.set_frames(frames);
  summary.set_slots(take->slots);
  STAGE_RETURN_IF_ERROR(records_->Create(row, take->dir, rig_.rig, schedule_, summary));
  {
    // The schedule as compiled, and as waveforms a logic-analyser viewer opens (the take's first 10 s at most).
    if (absl::Status s = WriteFileAtomically(take->dir + "/schedule.json", ToContractJson(schedule_)); !s.ok())
      say(std::string(s.message()));
    auto vcd = timing::ScheduleToVcd(schedule_, {0, std::min<int64_t>(take->slots, 10 * base.slot_rate_hz())});
    const absl::Status written = vcd.ok() ? WriteFileAtomically(take->dir + "/schedule.vcd", *vcd) : vcd.status();
    if (!written.ok()) say(absl::StrCat("schedule.vcd not written: ", written.message()));
  }
  say(absl::StrCat("take ", take->id, ": ", frames, " frames (", take->slots, " slots, ", row.duration_s, " s) into ",
                   take->dir, "; the slot clock: ", devices_.generator->Describe()));
  // Arm: every light node its table, every camera node its plan; the message names who is not ready.
  ArmLights(*take);
  ArmCameras(*take);
  if (!take->not_ready.empty()) say(absl::StrCat("not ready: ", absl::StrJoin(take->not_ready, ", ")));
  back.armed = true;
  SetState(v1::SESSION_STATE_ARMED);
  return take;
}

void Capturer::ArmLights(Take& take) {
  for (int i = 0; i < rig_.rig.light_nodes_size() && i < schedule_.light_nodes_size(); ++i) {
    const auto& node = rig_.rig.light_nodes(i);
    take.lights.push_back(devices_.nodes.light(node));
    v1::ArmLightRequest arm;
    arm.set_take_id(take.id);
    *arm.mutable_table() = schedule_.light_nodes(i).table();
    arm.set_take_slots(take.slots);
    arm.set_heartbeat_timeout_ms(kLightHeartbeatTimeoutMs);
    arm.set_start_at_planned_edge(devices_.generator->runs_free());
    v1::LightStats stats;
    const absl::Status armed = take.lights.back()->Arm(arm, StallDeadline(), &stats);
    take.light_armed.push_back(armed.ok());
    if (!armed.ok()) take.not_ready.push_back(absl::StrCat(node.id(), " (", armed.message(), ")"));
  }
  // The heartbeat: armed light nodes go dark when it stops (the controller died or lost them). One thread per node,
  // so that a node that hangs delays no other's. Its replies carry what the node saw of the take so far.
  for (size_t i = 0; i < take.lights.size(); ++i) {
    take.heartbeats.emplace_back([t = &take, i] {
      std::unique_lock<std::mutex> lock(t->heartbeat_mutex);
      while (!t->heartbeat_wake.wait_for(lock, std::chrono::milliseconds(kLightHeartbeatMs),
                                         [t] { return t->heartbeat_stop; })) {
        lock.unlock();
        v1::HeartbeatRequest beat;
        beat.set_take_id(t->id);
        v1::LightStats stats;
        // The deadline is the node's whole timeout, not the beat's period: on a starved machine a beat that takes
        // longer than a period to get through still resets the node's watchdog, where a cancelled one would not.
        const absl::Status s =
            t->lights[i]->Heartbeat(beat, std::chrono::milliseconds(kLightHeartbeatTimeoutMs), &stats);
        lock.lock();
        const int node = static_cast<int>(i);
        if (s.ok() && stats.take_faults_size() > 0) {
          t->light_faults[node].assign(stats.take_faults().begin(), stats.take_faults().end());
        }
        if (absl::IsUnavailable(s)) {
          t->light_refused_since.emplace(node, Clock::now());  // kept when already there
        } else {
          t->light_refused_since.erase(node);
        }
      }
    });
  }
}

void Capturer::ArmCameras(Take& take) {
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  for (int i = 0; i < rig_.rig.cameras_size() && i < schedule_.cameras_size(); ++i) {
    Take::Cam c{&rig_.rig.cameras(i), &schedule_.cameras(i), devices_.nodes.camera(rig_.rig.cameras(i))};
    c.path = absl::StrCat(take.dir, "/cameras/", c.config->id(), ".h5");
    v1::ArmCameraRequest arm;
    arm.set_take_id(take.id);
    arm.set_take_dir(take.dir);
    arm.set_start_later(true);
    arm.set_slot_rate_hz(base.slot_rate_hz());
    arm.set_slot_count(take.slots);
    arm.set_patterns_per_cycle(static_cast<uint32_t>(take.cycle));
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
    if (absl::Status s = c.client->Arm(arm, StallDeadline(), &armed); s.ok()) {
      c.armed = true;
      if (!armed.path().empty()) c.path = armed.path();
    } else {
      c.error = std::string(s.message());
      take.not_ready.push_back(absl::StrCat(c.config->id(), " (", s.message(), ")"));
    }
    take.cams.push_back(std::move(c));
  }
}

void Capturer::UpdateCameras(Take& take, bool with_t0) {
  v1::UpdateTakeRequest update;
  update.set_take_id(take.id);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (with_t0) update.set_t0_bus_ns(take.summary.t0_bus_ns());
    update.set_slot_count(take.slots);
    for (const auto& [first, end] : take.paused) {
      v1::SlotRange* r = update.add_paused();
      r->set_first(first);
      r->set_end(end);
    }
  }
  for (Take::Cam& c : take.cams) {
    if (!c.armed) continue;
    if (absl::Status s = c.client->UpdateTake(update, StallDeadline()); !s.ok()) {
      // It keeps what it recorded; its report is checked against the take's plan at the end.
      Say(absl::StrCat(c.config->id(), " did not take the new plan: ", s.message()), /*warn=*/true);
    }
  }
}

absl::StatusOr<SyncRun> Capturer::StartRun(Take& take, const SyncRunRequest& request,
                                           const std::function<void(const SyncRun&)>& apply) {
  SyncGenerator& generator = *devices_.generator;
  STAGE_ASSIGN_OR_RETURN(const SyncRun planned, generator.Plan(request, StallDeadline()));
  {
    std::lock_guard<std::mutex> lock(mutex_);
    apply(planned);
  }
  UpdateCameras(take, /*with_t0=*/true);
  if (generator.runs_free() && !take.ran) STAGE_RETURN_IF_ERROR(StartLights(take, planned.first_edge_ns));
  STAGE_ASSIGN_OR_RETURN(const SyncRun started, generator.Start(request, planned, StallDeadline()));
  if (started.first_slot != planned.first_slot || started.first_edge_ns != planned.first_edge_ns) {
    // The generator found its run only when it started (an external generator's first edge): the cameras hear again.
    {
      std::lock_guard<std::mutex> lock(mutex_);
      apply(started);
    }
    UpdateCameras(take, /*with_t0=*/true);
  }
  return started;
}

absl::Status Capturer::StartLights(Take& take, int64_t first_edge_ns) {
  // The clock runs free: every light node's table starts at the take's first edge. One that cannot would light the
  // take out of step, so the take does not start.
  v1::StartTableRequest start;
  start.set_take_id(take.id);
  start.set_first_edge_ns(first_edge_ns);
  for (size_t i = 0; i < take.lights.size(); ++i) {
    if (!take.light_armed[i]) continue;  // not ready at arming: named then, and dark
    if (absl::Status s = take.lights[i]->StartTable(start, StallDeadline()); !s.ok()) {
      return Annotate(s, absl::StrCat(rig_.rig.light_nodes(static_cast<int>(i)).id(),
                                      " could not start its table at the take's first edge"));
    }
  }
  return absl::OkStatus();
}

bool Capturer::StartTake(Take& take) {
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  SyncRunRequest request;
  request.slots = take.capture_slots;
  request.lead_slots = base.slot_rate_hz() / 2;  // real time: half a second to tell every node
  request.align_slots = take.cycle;
  request.first_of_take = true;
  // The run the take will be, planned first so that every camera knows its T0 before it starts.
  auto run = StartRun(take, request, [&](const SyncRun& r) {
    take.first_bus = r.first_slot;
    take.summary.set_t0_bus_ns(r.first_edge_ns);
  });
  if (!run.ok()) {
    Say(absl::StrCat("the sync generator (", devices_.generator->Describe(),
                     ") did not start the take: ", run.status().message()),
        /*warn=*/true);
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
  const bool abort_on_failure = rig_.rig.controller().node_failure_policy() == v1::NODE_FAILURE_POLICY_ABORT;
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
      state = session_.state();
      aborted = take.aborted;
    }
    v1::CaptureProgress progress;
    progress.set_phase(state == v1::SESSION_STATE_PAUSED     ? v1::CAPTURE_PHASE_PAUSED
                       : state == v1::SESSION_STATE_ABORTING ? v1::CAPTURE_PHASE_ABORTING
                                                             : v1::CAPTURE_PHASE_CAPTURING);
    TakeSnapshot snapshot;
    PollCameras(take, slots, gaps, state == v1::SESSION_STATE_CAPTURING, aborted, &progress, &snapshot);
    ReadClock(take, &snapshot);
    const TakeVerdict verdict = watch.Observe(snapshot, Clock::now());
    progress.set_frames_owed(watch.owed());
    progress.set_waiting_for(watch.waiting_for());
    progress.set_elapsed_s(std::chrono::duration<double>(Clock::now() - start).count());
    v1::CaptureEvent e;
    *e.mutable_progress() = progress;
    events_.Emit(e);
    if (const std::string lost = LostNode(take, snapshot);
        !lost.empty() && abort_on_failure && !aborted &&
        (state == v1::SESSION_STATE_CAPTURING || state == v1::SESSION_STATE_PAUSED)) {
      // controller.node_failure_policy: abort. What was recorded is kept; the take ends FAILED.
      std::lock_guard<std::mutex> control(control_mutex_);
      auto aborting = AbortRunning(take, state, lost);
      if (!aborting.ok()) Say(absl::StrCat("the take could not be aborted: ", aborting.status().message()), true);
      continue;
    }
    {
      // Decided under the lock, so that a pause either comes before this (and holds the take) or finds it finishing.
      std::lock_guard<std::mutex> lock(mutex_);
      // A pause, a resume or an abort on its way (its plan set, its state not yet) holds the take as a pause does.
      const bool changed = take.slots != slots || take.paused != gaps || session_.state() != state;
      if (changed || take.plan_changing || session_.state() == v1::SESSION_STATE_PAUSED) {
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
    std::this_thread::sleep_for(std::chrono::milliseconds(options_.poll_interval_ms));
  }
}

void Capturer::PollCameras(Take& take, int64_t slots, const Gaps& gaps, bool capturing, bool aborted,
                           v1::CaptureProgress* progress, TakeSnapshot* snapshot) {
  const auto now = Clock::now();
  for (Take::Cam& c : take.cams) {
    v1::RoleProgress* role = RoleOf(progress, c.config->role());
    // What the take has so far (its end moves with a pause, a resume, an abort), and, shown, what it will have.
    const int64_t expected = ExpectedFrames(*c.timing, slots, gaps);
    const int64_t shown = aborted ? expected : ExpectedFrames(*c.timing, take.capture_slots, {});
    role->set_expected(role->expected() + shown);
    progress->set_frames_expected(progress->frames_expected() + shown);
    if (!c.armed) continue;
    TakeSnapshot::Camera& seen = snapshot->cameras.emplace_back();
    seen.id = c.config->id();
    seen.expected = expected;
    v1::CameraStats stats;
    const absl::Status polled = c.client->GetStats(&stats);
    // Gone: refused for the drain (a reconnect refuses for a moment too), or answering without the take (it was
    // restarted): it delivers nothing more. Slow to answer: as it last said.
    if (absl::IsUnavailable(polled)) {
      if (!c.refused_since) c.refused_since = now;
      seen.down = now - *c.refused_since >= std::chrono::milliseconds(options_.drain_ms);
    } else {
      c.refused_since.reset();
    }
    if (polled.ok() && stats.take_id() != take.id) seen.down = true;
    if (seen.down && !c.lost) {
      c.lost = true;
      Say(absl::StrCat("camera ", c.config->id(),
                       " is lost: ", polled.ok() ? "its node answers without the take (restarted)" : polled.message()),
          /*warn=*/true);
    }
    if (!polled.ok() || stats.take_id() != take.id) continue;
    seen.answered = true;
    seen.received = stats.take_frames_received();
    seen.owed = stats.frames_owed();
    seen.work = stats.device_work();
    seen.activity = stats.device_activity();
    const int64_t got = std::min(stats.take_frames_received(), expected);
    role->set_received(role->received() + got);
    role->set_lost(role->lost() + stats.take_frames_lost());
    progress->set_frames_received(progress->frames_received() + got);
    progress->set_frames_written(progress->frames_written() + stats.take_frames_written());
    progress->set_frames_lost(progress->frames_lost() + stats.take_frames_lost());
    if (capturing && now >= c.next_preview) {
      // The console's view: the camera's latest full-on frame, small.
      c.next_preview = now + std::chrono::milliseconds(options_.preview_interval_ms);
      v1::GetPreviewRequest pr;
      pr.set_max_size(options_.preview_size);
      v1::Preview preview;
      if (c.client->GetPreview(pr, &preview).ok()) {
        std::lock_guard<std::mutex> lock(mutex_);
        previews_[c.config->id()] = std::move(preview);
      }
    }
  }
}

void Capturer::ReadClock(Take& take, TakeSnapshot* snapshot) {
  // The sync generator's run: how many of its edges it has produced.
  const auto now = Clock::now();
  const absl::StatusOr<SyncRun> run = devices_.generator->GetRun();
  std::string lost_now;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const int64_t run_first = take.first_bus + take.run_first, run_end = take.first_bus + take.run_end;
    const bool running = session_.state() == v1::SESSION_STATE_CAPTURING && !take.plan_changing;
    if (take.clock_lost.empty() && !run.ok()) {
      if (!take.clock_unanswered_since) take.clock_unanswered_since = now;
      if (running && now - *take.clock_unanswered_since >= std::chrono::milliseconds(options_.drain_ms)) {
        lost_now = absl::StrCat(devices_.generator->Describe(), " stopped answering (", run.status().message(),
                                ") after slot ", std::max<int64_t>(take.clock_current - take.first_bus, -1));
      }
    } else if (take.clock_lost.empty() && run.ok() && run->first_slot == run_first) {
      take.clock_unanswered_since.reset();
      take.clock_current = std::max(take.clock_current, run->current_slot);
      // A run that ended before the take's end, and no pause or abort ended it: the generator stopped on its own.
      if (running && run->end_slot < run_end && run->current_slot >= run->end_slot - 1) {
        lost_now = absl::StrCat(devices_.generator->Describe(), " ended the run at slot ",
                                run->end_slot - take.first_bus, ", before the take's end at slot ", take.run_end);
      }
    }
    if (!lost_now.empty()) {
      take.clock_lost = lost_now;
      take.clock_end = std::clamp<int64_t>(take.clock_current + 1 - take.first_bus, take.run_first, take.run_end);
    }
    if (!take.clock_lost.empty()) {
      // The clock produced its last edge: the run is over where it stopped.
      snapshot->clock_run_slots = std::max<int64_t>(0, take.clock_end - take.run_first);
      snapshot->clock_edges = snapshot->clock_run_slots;
    } else if (run.ok() && run->first_slot == run_first) {
      snapshot->clock_run_slots = run->end_slot - run->first_slot;
      snapshot->clock_edges =
          std::clamp<int64_t>(run->current_slot - run->first_slot + 1, 0, snapshot->clock_run_slots);
    }
  }
  if (!lost_now.empty()) Say(absl::StrCat("the slot clock is lost: ", lost_now), /*warn=*/true);
}

std::string Capturer::LostNode(Take& take, const TakeSnapshot& snapshot) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!take.clock_lost.empty()) return absl::StrCat("the sync generator: ", take.clock_lost);
  }
  for (const TakeSnapshot::Camera& c : snapshot.cameras) {
    if (c.down) return absl::StrCat("camera ", c.id, " is lost");
  }
  std::lock_guard<std::mutex> lock(take.heartbeat_mutex);
  for (const auto& [node, since] : take.light_refused_since) {
    if (Clock::now() - since >= std::chrono::milliseconds(options_.drain_ms)) {
      return absl::StrCat("light node ", rig_.rig.light_nodes(node).id(), " is lost");
    }
  }
  return "";
}

absl::StatusOr<v1::SessionReply> Capturer::Pause() {
  std::lock_guard<std::mutex> control(control_mutex_);
  Take* take;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (session_.state() != v1::SESSION_STATE_CAPTURING || running_ == nullptr) {
      return absl::FailedPreconditionError(
          absl::StrCat("pause: the session is ", SessionStateName(session_.state()), ", not capturing"));
    }
    take = running_;
    if (take->watch_ended) {
      return absl::FailedPreconditionError(absl::StrCat("pause: take ", take->id, " has ended; it is finishing"));
    }
    take->plan_changing = true;  // until the session says paused (or the pause fails)
  }
  const PlanSettled settled(&mutex_, &take->plan_changing);
  auto ended = devices_.generator->End(take->cycle);
  if (!ended.ok()) {
    return absl::FailedPreconditionError(
        absl::StrCat("pause: take ", take->id, " cannot stop at a frame boundary: ", ended.status().message()));
  }
  v1::SessionReply reply;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const int64_t at = ended->end_slot - take->first_bus;
    if (at >= take->run_end) {
      return absl::FailedPreconditionError(
          absl::StrCat("pause: take ", take->id, " is in its last frame; it ends at slot ", take->run_end));
    }
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
  reply.set_state(v1::SESSION_STATE_PAUSED);
  Logger("controller")->info("{}", reply.message());
  return reply;
}

absl::StatusOr<v1::SessionReply> Capturer::Resume() {
  std::lock_guard<std::mutex> control(control_mutex_);
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  Take* take;
  int64_t remaining, pause_at, min_gap, run_first_before;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (session_.state() != v1::SESSION_STATE_PAUSED || running_ == nullptr) {
      return absl::FailedPreconditionError(
          absl::StrCat("resume: the session is ", SessionStateName(session_.state()), ", not paused"));
    }
    take = running_;
    remaining = take->capture_slots - take->done_slots;
    pause_at = take->slots;
    run_first_before = take->run_first;
    // The gap is as long as the pause was (at least one frame), so that the take's slots stay the stage's time.
    const double paused_s = std::chrono::duration<double>(Clock::now() - take->paused_since).count();
    min_gap = std::max<int64_t>(take->cycle, static_cast<int64_t>(paused_s * base.slot_rate_hz()));
    take->plan_changing = true;  // until the session says capturing (or the resume fails)
  }
  const PlanSettled settled(&mutex_, &take->plan_changing);
  SyncRunRequest request;
  request.slots = remaining;
  request.lead_slots = base.slot_rate_hz() / 2;
  request.align_slots = take->cycle;
  request.min_first_slot = take->first_bus + pause_at + min_gap;
  bool applied = false;
  auto run = StartRun(*take, request, [&](const SyncRun& r) {
    const int64_t from = r.first_slot - take->first_bus;
    if (applied) take->paused.pop_back();
    applied = true;
    take->paused.emplace_back(pause_at, from);
    take->slots = from + remaining;
    take->run_first = from;
    take->run_end = take->slots;
  });
  if (!run.ok()) {
    // Still paused: the gap stays open until a resume that starts, or an abort.
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (applied) take->paused.pop_back();
      take->slots = pause_at;
      take->run_end = pause_at;
      take->run_first = run_first_before;
    }
    if (applied) UpdateCameras(*take, /*with_t0=*/false);
    return Annotate(run.status(), absl::StrCat("resume: take ", take->id, ": the sync generator"));
  }
  const int64_t from = run->first_slot - take->first_bus;
  SetState(v1::SESSION_STATE_CAPTURING);
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
    was = session_.state();
    if (was == v1::SESSION_STATE_ARMED && armed_ != nullptr) {
      armed = std::move(armed_);
      armed->aborted = true;
    } else if ((was == v1::SESSION_STATE_CAPTURING || was == v1::SESSION_STATE_PAUSED) && running_ != nullptr) {
      take = running_;
    } else {
      return absl::FailedPreconditionError(absl::StrCat("abort: the session is ", SessionStateName(was),
                                                        "; only an armed, capturing or paused take can be aborted"));
    }
  }
  if (take != nullptr) return AbortRunning(*take, was, "");
  // Nothing ran: the take ends here, with no frames.
  SetState(v1::SESSION_STATE_ABORTING);
  const std::string id = armed->id;
  STAGE_RETURN_IF_ERROR(FinalizeTake(*armed).status());
  v1::SessionReply reply;
  reply.set_state(state());
  reply.set_take_id(id);
  reply.set_message(absl::StrCat("take ", id, " aborted before it started"));
  return reply;
}

absl::StatusOr<v1::SessionReply> Capturer::AbortRunning(Take& take, v1::SessionState was, const std::string& why) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (take.watch_ended) {
      return absl::FailedPreconditionError(absl::StrCat("abort: take ", take.id, " has ended; it is finishing"));
    }
    take.plan_changing = true;  // until the session says aborting
  }
  const PlanSettled settled(&mutex_, &take.plan_changing);
  bool clock_lost;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    clock_lost = !take.clock_lost.empty();
  }
  // The run ends at the next slot (a lost generator cannot be asked: its slots from where it stopped are lost).
  if (was == v1::SESSION_STATE_CAPTURING && !clock_lost) {
    auto ended = devices_.generator->End(1);
    if (!ended.ok()) {
      return absl::FailedPreconditionError(
          absl::StrCat("abort: take ", take.id, " cannot be stopped: ", ended.status().message()));
    }
    std::lock_guard<std::mutex> lock(mutex_);
    const int64_t at = ended->end_slot - take.first_bus;
    take.done_slots += std::min(at, take.run_end) - take.run_first;
    take.run_end = std::min(at, take.run_end);
    take.slots = take.run_end;
  }
  int64_t at;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    take.aborted = true;
    take.abort_reason = why;
    at = take.slots;
  }
  UpdateCameras(take, /*with_t0=*/false);
  SetState(v1::SESSION_STATE_ABORTING);
  v1::SessionReply reply;
  reply.set_state(v1::SESSION_STATE_ABORTING);
  reply.set_take_id(take.id);
  reply.set_slot(at);
  reply.set_message(why.empty() ? absl::StrCat("take ", take.id, " aborted at slot ", at, "; what it recorded is kept")
                                : absl::StrCat("take ", take.id, " aborted at slot ", at, " (", why,
                                               "; controller.node_failure_policy: abort); what it recorded is kept"));
  Say(reply.message(), /*warn=*/!why.empty());
  return reply;
}

absl::Status Capturer::ClaimArming(const char* what) {
  // With mutex_ held. The check and the claim are one step: two requests cannot both arm.
  if (session_.state() != v1::SESSION_STATE_IDLE && session_.state() != v1::SESSION_STATE_ERROR) {
    return absl::FailedPreconditionError(
        absl::StrCat(what, ": the session is ", SessionStateName(session_.state()), "; wait for it"));
  }
  if (arming_) return absl::FailedPreconditionError(absl::StrCat(what, ": another take is being armed; wait for it"));
  arming_ = true;
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<Capturer::Take>> Capturer::ArmClaimed(const v1::CaptureRequest& request) {
  auto take = ArmTake(request);
  std::lock_guard<std::mutex> lock(mutex_);
  arming_ = false;
  return take;
}

absl::StatusOr<v1::TakeSummary> Capturer::Arm(const v1::CaptureRequest& request, const CaptureEventFn& on_event) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    STAGE_RETURN_IF_ERROR(ClaimArming("arm"));
  }
  Following following(&events_, on_event);
  STAGE_ASSIGN_OR_RETURN(std::unique_ptr<Take> take, ArmClaimed(request));
  v1::TakeSummary summary = take->summary;
  std::lock_guard<std::mutex> lock(mutex_);
  armed_ = std::move(take);
  return summary;
}

absl::StatusOr<v1::TakeSummary> Capturer::Capture(const v1::CaptureRequest& request, const CaptureEventFn& on_event) {
  std::unique_ptr<Take> take;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const v1::SessionState state = session_.state();
    if (state == v1::SESSION_STATE_ARMED && armed_ != nullptr) {
      const int64_t frames = armed_->capture_slots / armed_->cycle;
      if (request.frames() > 0 && request.frames() != frames) {
        return absl::InvalidArgumentError(absl::StrCat("capture: take ", armed_->id, " is armed for ", frames,
                                                       " frames, not ", request.frames(),
                                                       "; capture it as armed, or abort it"));
      }
      take = std::move(armed_);
      running_ = take.get();
    } else {
      STAGE_RETURN_IF_ERROR(ClaimArming("capture"));
    }
  }
  // The caller follows the take's events until it ends (or goes away: the take goes on).
  Following following(&events_, on_event);
  if (take == nullptr) {
    STAGE_ASSIGN_OR_RETURN(take, ArmClaimed(request));
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
  if (state() != v1::SESSION_STATE_ABORTING) SetState(v1::SESSION_STATE_FINALIZING);
  TakeShape shape;
  TakeCircumstances why;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    shape.slots = take.ran ? take.slots : 0;
    shape.gaps = take.paused;
    shape.clock_end = take.clock_end;
    shape.clock_lost = take.clock_lost;
    why.aborted = take.aborted;
    why.abort_reason = take.abort_reason;
    why.done_slots = take.done_slots;
    why.clock_lost = take.clock_lost;
  }
  shape.cycle = take.cycle;
  shape.ran = take.ran;
  why.capture_slots = take.capture_slots;
  why.not_ready = take.not_ready;
  why.stalled = take.stalled;
  v1::TakeSummary& summary = take.summary;
  summary.set_slots(shape.slots);
  summary.set_aborted(why.aborted);
  for (const auto& [first, end] : shape.gaps) {
    v1::SlotRange* r = summary.add_paused();
    r->set_first(first);
    r->set_end(end);
  }

  const std::vector<CameraOutcome> cameras = FinishCameras(take, shape);
  std::vector<storage::LedgerEntry> ledger;
  auto say = [&](const std::string& m) { Say(m); };
  for (const CameraOutcome& c : cameras) {
    AccountCamera(shape, c, have_signature_ ? &signature_ : nullptr, &summary, &ledger, say);
  }
  why.light_faults = LightFaults(take);
  WriteTruth(take, shape);

  // The verdict, and what is kept of the take.
  const v1::TakeOutcome outcome = JudgeTake(shape, why, &summary);
  const v1::LedgerCounts& total = summary.total();
  storage::TakeRow& row = take.row;
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  row.state = why.aborted                            ? v1::TAKE_STATE_ABORTED
              : outcome == v1::TAKE_OUTCOME_COMPLETE ? v1::TAKE_STATE_COMPLETE
              : outcome == v1::TAKE_OUTCOME_DEGRADED ? v1::TAKE_STATE_DEGRADED
                                                     : v1::TAKE_STATE_FAILED;
  row.outcome = outcome;
  row.slots = shape.slots;
  row.duration_s = static_cast<double>(shape.slots) / base.slot_rate_hz();
  row.frames_expected = total.expected();
  row.frames_stored = total.stored();
  row.size_bytes = static_cast<int64_t>(summary.bytes());
  if (absl::Status kept = records_->Keep(row, ledger, take.dir, rig_.rig, schedule_, summary); !kept.ok()) {
    // The take's records are incomplete: the operator must know before the next take.
    Say(absl::StrCat("take ", take.id, ": its records could not be kept: ", kept.message()));
    SetState(v1::SESSION_STATE_ERROR);
    return kept;
  }
  CountTake(row.state, row.frames_expected, row.frames_stored);
  EmitDone(take, cameras);
  Logger("controller")
      ->info("take {}: {} ({} of {} frames stored)", take.id, TakeOutcomeName(outcome), total.stored(),
             total.expected());
  SetState(v1::SESSION_STATE_IDLE);
  return summary;
}

std::vector<CameraOutcome> Capturer::FinishCameras(Take& take, const TakeShape& shape) {
  // Every camera accounts for its slots, all at once (a burst offload takes its time).
  std::vector<CameraOutcome> out(take.cams.size());
  std::vector<std::thread> finishing;
  std::atomic<size_t> done{0};
  // Set (release) once a camera's Finish has returned: its outcome is then what it reported.
  std::unique_ptr<std::atomic<bool>[]> finished(new std::atomic<bool>[take.cams.size()]);
  for (size_t i = 0; i < take.cams.size(); ++i) {
    finished[i].store(false);
    out[i].config = take.cams[i].config;
    out[i].timing = take.cams[i].timing;
    out[i].path = take.cams[i].path;
    out[i].error = take.cams[i].error;
  }
  for (size_t i = 0; i < take.cams.size(); ++i) {
    if (!take.cams[i].armed) continue;
    finishing.emplace_back([&, i] {
      v1::FinishCameraRequest finish;
      finish.set_take_id(take.id);
      finish.set_drain_ms(static_cast<uint32_t>(take.ran ? options_.drain_ms : 1));
      v1::CameraTakeReport report;
      const absl::Status s =
          take.cams[i].client->Finish(finish, std::chrono::milliseconds(options_.drain_ms + 600'000), &report);
      if (s.ok()) {
        out[i].report = std::move(report);
      } else {
        out[i].error = std::string(s.message());
      }
      finished[i].store(true, std::memory_order_release);
      done.fetch_add(1);
    });
  }
  // Meanwhile: what the burst cameras have written of what they held (their offload after the take).
  int64_t to_write = 0;
  for (const Take::Cam& c : take.cams) {
    if (c.armed && c.config->role() == v1::CAMERA_ROLE_HIGH_SPEED)
      to_write += ExpectedFrames(*c.timing, shape.slots, shape.gaps);
  }
  while (done.load() < finishing.size()) {
    std::this_thread::sleep_for(std::chrono::milliseconds(std::min(500, options_.poll_interval_ms * 2)));
    if (done.load() >= finishing.size() || to_write == 0) continue;
    v1::CaptureProgress progress;
    progress.set_phase(v1::CAPTURE_PHASE_OFFLOADING);
    progress.set_frames_expected(to_write);
    for (size_t i = 0; i < take.cams.size(); ++i) {
      Take::Cam& c = take.cams[i];
      if (!c.armed || c.config->role() != v1::CAMERA_ROLE_HIGH_SPEED) continue;
      if (finished[i].load(std::memory_order_acquire)) {
        progress.set_frames_written(progress.frames_written() + (out[i].report ? out[i].report->frames_written() : 0));
        continue;
      }
      v1::CameraStats stats;
      if (c.client->GetStats(&stats).ok() && stats.take_id() == take.id) {
        progress.set_frames_written(progress.frames_written() + stats.take_frames_written());
      }
    }
    v1::CaptureEvent e;
    *e.mutable_progress() = progress;
    events_.Emit(e);
  }
  for (std::thread& t : finishing) t.join();
  return out;
}

std::vector<std::string> Capturer::LightFaults(Take& take) {
  std::vector<std::string> hints;
  const std::vector<LightDisarmed> disarmed = DisarmLights(take);
  for (size_t i = 0; i < take.lights.size(); ++i) {
    const std::string& node_id = rig_.rig.light_nodes(static_cast<int>(i)).id();
    std::vector<std::string> faults;
    {
      std::lock_guard<std::mutex> lock(take.heartbeat_mutex);
      faults = take.light_faults[static_cast<int>(i)];
    }
    if (!disarmed[i].error.empty()) {
      Say(absl::StrCat("light node ", node_id, " did not disarm: ", disarmed[i].error));
      faults.push_back(absl::StrCat("did not disarm: ", disarmed[i].error));
    } else if (disarmed[i].stats.take_faults_size() > 0) {
      faults.assign(disarmed[i].stats.take_faults().begin(), disarmed[i].stats.take_faults().end());
    }
    // A node that went dark during the take on its own (its watchdog, its board): the frames after it are unlit, and
    // the next take cannot arm it until it is reset. An emergency stop, which darkened every node and aborted the
    // take, is said once by the abort, not once a node.
    std::string estop_reason;
    const bool estop = options_.estop != nullptr && options_.estop->latched(&estop_reason);
    if (disarmed[i].error.empty() && !disarmed[i].stats.blackout_reason().empty() &&
        !(estop && disarmed[i].stats.blackout_reason().find(estop_reason) != std::string::npos)) {
      faults.push_back(absl::StrCat("went dark during the take (", disarmed[i].stats.blackout_reason(),
                                    "); reset it before the next take (stagectl estop --reset)"));
    }
    for (const std::string& f : faults) {
      Say(absl::StrCat("light node ", node_id, ": ", f));
      hints.push_back(absl::StrCat(node_id, ": ", f));
    }
  }
  return hints;
}

void Capturer::WriteTruth(Take& take, const TakeShape& shape) {
  if (devices_.truth == nullptr || !take.ran || take.ground_truth == v1::GROUND_TRUTH_SCOPE_NONE || shape.slots <= 0) {
    return;
  }
  // The take's frames that ran [first, end), in frames of the take: not its pauses', nor after a lost clock.
  const int64_t slots = shape.clock_end >= 0 ? shape.clock_end : shape.slots;
  std::vector<std::pair<int64_t, int64_t>> runs;
  int64_t from = 0;
  for (const auto& [first, end] : shape.gaps) {
    if (first > from) runs.emplace_back(from / take.cycle, (first + take.cycle - 1) / take.cycle);
    from = end;
  }
  if (slots > from) runs.emplace_back(from / take.cycle, (slots + take.cycle - 1) / take.cycle);
  int64_t frames = 0;
  for (const auto& [first, end] : runs) frames += end - first;
  if (frames == 0) return;
  const std::string dir = take.dir + "/ground_truth";
  Say(absl::StrCat("writing the ground truth of ", frames, " frame(s) to ", dir));
  const int64_t bus_frame = take.first_bus / take.cycle;
  for (const auto& [first, end] : runs) {
    const absl::Status s = devices_.truth->Write(dir, bus_frame, bus_frame + first, end - first,
                                                 take.ground_truth == v1::GROUND_TRUTH_SCOPE_SCENE);
    if (!s.ok()) {
      if (!absl::IsUnimplemented(s)) Say(absl::StrCat("no ground truth: ", s.message()));
      take.summary.clear_ground_truth_dir();
      return;
    }
    take.summary.set_ground_truth_dir(dir);
  }
}

void Capturer::EmitDone(Take& take, const std::vector<CameraOutcome>& cameras) {
  const v1::TakeSummary& summary = take.summary;
  const v1::LedgerCounts& total = summary.total();
  v1::CaptureEvent done;
  v1::CaptureProgress* p = done.mutable_progress();
  p->set_phase(v1::CAPTURE_PHASE_DONE);
  p->set_frames_expected(total.expected());
  p->set_frames_received(total.stored());
  p->set_frames_lost(total.expected() - total.stored());
  for (size_t i = 0; i < cameras.size(); ++i) {
    const v1::CameraTakeSummary& cs = summary.cameras(static_cast<int>(i));
    v1::RoleProgress* role = RoleOf(p, cs.role());
    role->set_expected(role->expected() + cs.counts().expected());
    role->set_received(role->received() + cs.counts().stored());
    role->set_lost(role->lost() + cs.counts().expected() - cs.counts().stored());
    if (cameras[i].report) p->set_frames_written(p->frames_written() + cameras[i].report->frames_written());
  }
  p->set_elapsed_s(std::chrono::duration<double>(Clock::now() - take.armed_at).count());
  events_.Emit(done);
  v1::CaptureEvent last;
  *last.mutable_summary() = summary;
  events_.Emit(last);
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
      if (absl::Status s = take.lights[i]->Disarm(disarm, give_up, &out[i].stats); !s.ok()) {
        out[i].error = std::string(s.message());
      }
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
    return absl::NotFoundError(take_id.empty()
                                   ? "no take is running (the session is " + SessionStateName(session_.state()) + ")"
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
  return records_->GetLedger(request);
}

absl::StatusOr<v1::TakeList> Capturer::ListTakes() const { return records_->ListTakes(); }

absl::StatusOr<v1::TakeSummary> Capturer::GetTake(const std::string& id) const { return records_->GetTake(id); }

}  // namespace stage::controller
