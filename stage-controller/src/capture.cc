// Capturing takes: see capture.h.
#include "capture.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/clock.h"
#include "stage/common/file_util.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/status.h"
#include "stage/common/version.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"
#include "stage/timing/waveform.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/light_node.grpc.pb.h"
#include "stage/v1/sim.grpc.pb.h"

namespace stage::controller {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

std::string ToJson(const google::protobuf::Message& m) {
  google::protobuf::util::JsonPrintOptions o;
  o.add_whitespace = true;
  o.preserve_proto_field_names = true;
  o.always_print_primitive_fields = true;
  std::string out;
  (void)google::protobuf::util::MessageToJsonString(m, &out, o);
  return out;
}

void Deadline(grpc::ClientContext* c, int ms) {
  c->set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(ms));
}

void Add(v1::LedgerCounts* c, storage::LossReason reason) {
  c->set_expected(c->expected() + 1);
  const bool stored = reason == storage::LossReason::kNone || reason == storage::LossReason::kIncomplete;
  if (stored) c->set_stored(c->stored() + 1);
  if (reason != storage::LossReason::kNone) (*c->mutable_lost())[storage::LossReasonName(reason)] += 1;
}

// take.json: what the take was and how it ended (docs/storage.md).
absl::Status WriteTakeJson(const std::string& dir, const v1::RigConfig& rig, const v1::Schedule& schedule,
                           const v1::TakeSummary& summary, const std::string& state) {
  std::string text =
      absl::StrCat("{\n\"format\": \"fastage-take-1\",\n\"software\": \"FaStage ", kVersion, "\",\n\"state\": \"",
                   state, "\",\n\"schedule_hash\": \"", schedule.hash(), "\",\n\"rig_hash\": \"", schedule.rig_hash(),
                   "\",\n\"summary\": ", ToJson(summary), ",\n\"rig\": ", ToJson(rig), "\n}\n");
  return WriteFileAtomically(dir + "/take.json", text);  // a reader sees the old file or the new one
}

}  // namespace

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

std::string Capturer::state() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return state_;
}

void Capturer::SetState(const std::string& state, const std::function<void(const v1::CaptureEvent&)>& on_event) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    Logger("controller")->info("session: {} -> {}", state_, state);
    state_ = state;
  }
  v1::CaptureEvent e;
  e.set_state(state);
  if (on_event) on_event(e);
}

absl::StatusOr<v1::TakeSummary> Capturer::Capture(const v1::CaptureRequest& request,
                                                  const std::function<void(const v1::CaptureEvent&)>& on_event) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (state_ != "idle") return absl::FailedPreconditionError(absl::StrCat("a take is ", state_, "; wait for it"));
  }
  const timing::TimeBase base = timing::TimeBase::FromProto(schedule_.time_base());
  const int64_t cycle = schedule_.patterns_size();
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
  if (options_.world_address.empty()) {
    return absl::FailedPreconditionError(
        "no sync generator: the controller drives the simulated world's bus (stage-sim); a hardware slot clock comes "
        "with the light-node work");
  }
  auto emit = [&](const v1::CaptureEvent& e) {
    if (on_event) on_event(e);
  };
  auto say = [&](const std::string& m) {
    Logger("controller")->info("{}", m);
    v1::CaptureEvent e;
    e.set_message(m);
    emit(e);
  };
  SetState("configuring", on_event);
  struct Idle {
    Capturer* c;
    const std::function<void(const v1::CaptureEvent&)>& f;
    ~Idle() { c->SetState("idle", f); }
  } idle{this, on_event};

  const int64_t slots = frames * cycle;
  const int64_t now_unix = RealClock(RealClock::Kind::kRealtime).NowNs();
  STAGE_ASSIGN_OR_RETURN(std::string take_id, catalog_->NextTakeId(rig_.rig.stage().id(), now_unix));
  const std::string dir = (fs::path(options_.take_root) / take_id).string();
  std::error_code ec;
  fs::create_directories(dir + "/cameras", ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  storage::TakeRow row;
  row.id = take_id;
  row.name = request.name();
  row.state = "configuring";
  row.created_unix_ns = now_unix;
  row.slots = slots;
  row.duration_s = static_cast<double>(slots) / base.slot_rate_hz();
  row.rig_hash = schedule_.rig_hash();
  row.schedule_hash = schedule_.hash();
  row.dir = take_id;
  STAGE_RETURN_IF_ERROR(catalog_->CreateTake(row));
  v1::TakeSummary summary;
  summary.set_take_id(take_id);
  summary.set_name(request.name());
  summary.set_dir(dir);
  summary.set_frames(frames);
  summary.set_slots(slots);
  STAGE_RETURN_IF_ERROR(WriteTakeJson(dir, rig_.rig, schedule_, summary, "configuring"));
  {
    // The schedule as compiled, and as waveforms a logic-analyser viewer opens (the take's first 10 s at most).
    if (absl::Status s = WriteFileAtomically(dir + "/schedule.json", ToJson(schedule_)); !s.ok())
      say(std::string(s.message()));
    auto vcd = timing::ScheduleToVcd(schedule_, {0, std::min<int64_t>(slots, 10 * base.slot_rate_hz())});
    const absl::Status written = vcd.ok() ? WriteFileAtomically(dir + "/schedule.vcd", *vcd) : vcd.status();
    if (!written.ok()) say(absl::StrCat("schedule.vcd not written: ", written.message()));
  }
  say(absl::StrCat("take ", take_id, ": ", frames, " frames (", slots, " slots, ", row.duration_s, " s) into ", dir));

  // The run of the bus the take will be: planned first, so that every node is armed for it before it starts.
  auto world = v1::SimWorld::NewStub(grpc::CreateChannel(options_.world_address, grpc::InsecureChannelCredentials()));
  v1::RunWorldRequest plan;
  plan.set_slots(slots);
  plan.set_lead_slots(base.slot_rate_hz() / 2);  // real time: half a second to arm every node
  plan.set_align_slots(cycle);
  plan.set_plan_only(true);
  v1::WorldRunReply run;
  {
    grpc::ClientContext context;
    Deadline(&context, 5000);
    grpc::Status s = world->Run(&context, plan, &run);
    if (!s.ok()) return Annotate(FromGrpcStatus(s), absl::StrCat("the simulated world at ", options_.world_address));
  }
  summary.set_t0_bus_ns(run.first_edge_ns());

  // Arm: every light node its table, every camera node its plan; the message names who is not ready.
  std::vector<std::string> not_ready;
  std::vector<std::unique_ptr<v1::LightNode::Stub>> lights;
  for (int i = 0; i < rig_.rig.light_nodes_size() && i < schedule_.light_nodes_size(); ++i) {
    const auto& node = rig_.rig.light_nodes(i);
    lights.push_back(v1::LightNode::NewStub(grpc::CreateChannel(node.address(), grpc::InsecureChannelCredentials())));
    v1::ArmLightRequest arm;
    arm.set_take_id(take_id);
    *arm.mutable_table() = schedule_.light_nodes(i).table();
    grpc::ClientContext context;
    Deadline(&context, options_.arm_timeout_ms);
    v1::LightStats stats;
    grpc::Status s = lights.back()->Arm(&context, arm, &stats);
    if (!s.ok()) not_ready.push_back(absl::StrCat(node.id(), " (", s.error_message(), ")"));
  }
  struct Cam {
    const v1::CameraConfig* config;
    const v1::CameraTiming* timing;
    std::unique_ptr<v1::CameraNode::Stub> stub;
    int64_t expected = 0;
    bool armed = false;
    std::string error;
  };
  std::vector<Cam> cams;
  for (int i = 0; i < rig_.rig.cameras_size() && i < schedule_.cameras_size(); ++i) {
    Cam c{&rig_.rig.cameras(i), &schedule_.cameras(i),
          v1::CameraNode::NewStub(
              grpc::CreateChannel(rig_.rig.cameras(i).address(), grpc::InsecureChannelCredentials()))};
    const uint32_t d = std::max<uint32_t>(1, c.timing->divider());
    c.expected = timing::FiringsInTake(*c.timing, slots);
    v1::ArmCameraRequest arm;
    arm.set_take_id(take_id);
    arm.set_take_dir(dir);
    arm.set_t0_bus_ns(run.first_edge_ns());
    arm.set_slot_rate_hz(base.slot_rate_hz());
    arm.set_slot_count(slots);
    arm.set_patterns_per_cycle(static_cast<uint32_t>(cycle));
    arm.mutable_trigger_plan()->set_source(c.timing->source());
    arm.mutable_trigger_plan()->set_divider(d);
    arm.mutable_trigger_plan()->set_slot_phase(c.timing->slot_phase());
    arm.set_trigger_delay_ns(base.TicksToNs(c.timing->trigger_ticks()));
    const bool hs = c.config->role() == v1::CAMERA_ROLE_HIGH_SPEED;
    arm.set_burst(hs);
    if (hs) arm.set_burst_bytes(static_cast<uint64_t>(c.config->ram_gib() * (1ull << 30)));
    grpc::ClientContext context;
    Deadline(&context, options_.arm_timeout_ms);
    v1::ArmCameraResponse armed;
    grpc::Status s = c.stub->Arm(&context, arm, &armed);
    if (s.ok()) {
      c.armed = true;
    } else {
      c.error = s.error_message();
      not_ready.push_back(absl::StrCat(c.config->id(), " (", s.error_message(), ")"));
    }
    cams.push_back(std::move(c));
  }
  const bool abort_on_failure = rig_.rig.controller().node_failure_policy() == v1::NODE_FAILURE_POLICY_ABORT;
  bool ran = false;
  if (!not_ready.empty()) {
    say(absl::StrCat("not ready: ", absl::StrJoin(not_ready, ", ")));
  }
  if (not_ready.empty() || !abort_on_failure) {
    SetState("armed", on_event);
    v1::RunWorldRequest start = plan;
    start.set_plan_only(false);
    start.set_first_slot(run.first_slot());
    grpc::ClientContext context;
    Deadline(&context, 5000);
    v1::WorldRunReply started;
    grpc::Status s = world->Run(&context, start, &started);
    if (!s.ok()) {
      say(absl::StrCat("the sync generator did not start: ", s.error_message()));
    } else {
      ran = true;
      SetState("capturing", on_event);
    }
  }

  // Watch: every camera's frames for the take, until all are in or nothing has come for a while (a node down, the
  // bus ended); in real time not before the take's last slot has passed.
  if (ran) {
    const auto start = Clock::now();
    int64_t last_total = -1;
    auto last_change = Clock::now();
    while (true) {
      v1::CaptureProgress progress;
      int64_t total = 0;
      for (Cam& c : cams) {
        const std::string role = CameraRoleName(c.config->role());
        (*progress.mutable_expected_by_role())[role] += c.expected;
        progress.set_frames_expected(progress.frames_expected() + c.expected);
        if (!c.armed) continue;
        grpc::ClientContext context;
        Deadline(&context, 1000);
        v1::CameraStats stats;
        if (!c.stub->GetStats(&context, v1::GetStatsRequest(), &stats).ok() || stats.take_id() != take_id) continue;
        const int64_t got = std::min(stats.take_frames_received(), c.expected);
        (*progress.mutable_received_by_role())[role] += got;
        progress.set_frames_received(progress.frames_received() + got);
        progress.set_frames_written(progress.frames_written() + stats.take_frames_written());
        total += got;
      }
      progress.set_elapsed_s(std::chrono::duration<double>(Clock::now() - start).count());
      v1::CaptureEvent e;
      *e.mutable_progress() = progress;
      emit(e);
      if (total >= progress.frames_expected()) break;
      if (total != last_total) {
        last_total = total;
        last_change = Clock::now();
      }
      // Silence ends the watch: no camera got a frame for a while (a node down, the bus ended, frames lost).
      if (Clock::now() - last_change > std::chrono::milliseconds(options_.drain_ms) + std::chrono::seconds(5)) {
        say("frames stopped coming before every camera had all of its frames; finishing the take");
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(250));
    }
  }

  // Finish: every camera accounts for its slots; lights go dark.
  SetState("finalizing", on_event);
  std::vector<storage::LedgerEntry> ledger;
  v1::LedgerCounts* total = summary.mutable_total();
  uint64_t bytes = 0;
  for (Cam& c : cams) {
    v1::CameraTakeSummary* cs = summary.add_cameras();
    cs->set_camera_id(c.config->id());
    cs->set_role(CameraRoleName(c.config->role()));
    v1::CameraTakeReport report;
    bool reported = false;
    if (c.armed) {
      v1::FinishCameraRequest finish;
      finish.set_take_id(take_id);
      finish.set_drain_ms(static_cast<uint32_t>(options_.drain_ms));
      grpc::ClientContext context;
      Deadline(&context, options_.drain_ms + 600'000);  // a burst offload takes its time
      grpc::Status s = c.stub->Finish(&context, finish, &report);
      if (s.ok()) {
        reported = true;
      } else {
        c.error = s.error_message();
      }
    }
    const uint32_t d = std::max<uint32_t>(1, c.timing->divider());
    if (reported) {
      cs->set_path(report.path());
      cs->set_bytes(report.bytes());
      cs->set_error(report.error());
      bytes += report.bytes();
      for (const v1::SlotRecord& r : report.slots()) {
        storage::LedgerEntry e{c.config->id(),
                               r.slot(),
                               r.pattern(),
                               static_cast<storage::LossReason>(r.reason()),
                               r.has_frame_id() ? std::optional<uint64_t>(r.frame_id()) : std::nullopt,
                               r.detail()};
        Add(cs->mutable_counts(), e.reason);
        Add(total, e.reason);
        ledger.push_back(std::move(e));
      }
      if (c.config->role() == v1::CAMERA_ROLE_HIGH_SPEED && have_signature_) {
        std::map<int64_t, double> brightness;
        for (int i = 0; i < report.brightness_slots_size() && i < report.brightness_size(); ++i) {
          brightness[report.brightness_slots(i)] = report.brightness(i);
        }
        const timing::AlignmentReport a = timing::CheckAlignment(signature_, static_cast<int>(cycle), brightness);
        v1::AlignmentSummary* as = summary.add_alignment();
        as->set_camera_id(c.config->id());
        as->set_ok(a.ok);
        as->set_shift(a.shift);
        as->set_residual(a.residual);
        for (int64_t b : a.bad_cycles) as->add_bad_cycles(b);
        as->set_message(a.message);
      }
    } else {
      // The node never armed or cannot report: every slot it was to fire in is lost to it.
      cs->set_error(c.error.empty() ? "did not report" : c.error);
      for (int64_t k = c.timing->slot_phase(); k < slots; k += d) {
        storage::LedgerEntry e{
            c.config->id(), k,          static_cast<int32_t>(k % cycle), storage::LossReason::kNodeDown,
            std::nullopt,   cs->error()};
        Add(cs->mutable_counts(), e.reason);
        Add(total, e.reason);
        ledger.push_back(std::move(e));
      }
    }
  }
  for (size_t i = 0; i < lights.size(); ++i) {
    v1::DisarmLightRequest disarm;
    disarm.set_take_id(take_id);
    grpc::ClientContext context;
    Deadline(&context, 2000);
    v1::LightStats stats;
    if (!lights[i]->Disarm(&context, disarm, &stats).ok()) {
      say(absl::StrCat("light node ", rig_.rig.light_nodes(static_cast<int>(i)).id(), " did not disarm"));
    }
  }
  STAGE_RETURN_IF_ERROR(catalog_->RecordLedger(take_id, ledger));

  // The verdict, and what to do about it.
  std::vector<std::string> hints;
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
    for (const auto& [reason, n] : cs.counts().lost()) {
      if (reason != "incomplete") why.push_back(absl::StrCat(n, " ", reason));
    }
    hints.push_back(absl::StrCat(cs.camera_id(), " lost ", lost, " (", absl::StrJoin(why, ", "), ")"));
  }
  std::string outcome = "COMPLETE";
  if (!ran || total->stored() == 0) {
    outcome = "FAILED";
  } else if (total->stored() < total->expected() || !aligned) {
    outcome = "DEGRADED";
  }
  summary.set_outcome(outcome);
  summary.set_bytes(bytes);
  if (!hints.empty()) {
    if (hints.size() > 6) {
      const size_t more = hints.size() - 5;
      hints.resize(5);
      hints.push_back(absl::StrCat("and ", more, " more"));
    }
    summary.set_hint(absl::StrCat(outcome == "COMPLETE" ? "" : "retake? ", absl::StrJoin(hints, "; ")));
  }
  row.state = outcome == "COMPLETE" ? "complete" : outcome == "DEGRADED" ? "degraded" : "failed";
  row.outcome = outcome;
  row.t0_unix_ns = now_unix;
  row.frames_expected = total->expected();
  row.frames_stored = total->stored();
  row.size_bytes = static_cast<int64_t>(bytes);
  STAGE_RETURN_IF_ERROR(catalog_->UpdateTake(row));
  STAGE_RETURN_IF_ERROR(WriteTakeJson(dir, rig_.rig, schedule_, summary, row.state));
  v1::CaptureEvent last;
  *last.mutable_summary() = summary;
  emit(last);
  Logger("controller")
      ->info("take {}: {} ({} of {} frames stored)", take_id, outcome, total->stored(), total->expected());
  return summary;
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
  STAGE_ASSIGN_OR_RETURN(storage::TakeRow row, catalog_->GetTake(id));
  const std::string path = (fs::path(options_.take_root) / row.dir / "take.json").string();
  auto text = ReadFileToString(path);
  if (!text.ok()) return text.status();
  nlohmann::json take = nlohmann::json::parse(*text, nullptr, /*allow_exceptions=*/false);
  if (take.is_discarded() || !take.contains("summary")) {
    return absl::DataLossError(absl::StrCat(path, ": not a take file with a summary"));
  }
  v1::TakeSummary summary;
  google::protobuf::util::JsonParseOptions o;
  o.ignore_unknown_fields = true;
  auto s = google::protobuf::util::JsonStringToMessage(take["summary"].dump(), &summary, o);
  if (!s.ok()) return absl::DataLossError(absl::StrCat(path, ": ", s.message().as_string()));
  return summary;
}

}  // namespace stage::controller
