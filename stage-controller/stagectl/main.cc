// stagectl: the command-line console of the stage (a thin StageController client; `timing` also works on a rig file
// without a controller).
#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_replace.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "fmt/format.h"
#include "stage/common/cli.h"
#include "stage/common/file_util.h"
#include "stage/common/grpc_status.h"
#include "stage/common/ledger_counts.h"
#include "stage/common/logging.h"
#include "stage/common/processing_names.h"
#include "stage/common/proto_json.h"
#include "stage/common/rig.h"
#include "stage/common/rig_security.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/stage_locator.h"
#include "stage/common/status.h"
#include "stage/common/take_names.h"
#include "stage/common/version.h"
#include "stage/timing/timing_tool.h"
#include "stage/v1/camera_node.grpc.pb.h"
#include "stage/v1/controller.grpc.pb.h"
#include "stage/v1/sim.grpc.pb.h"
#include "status_format.h"

namespace {

constexpr const char* kProgram = "stagectl";
// Exit code when the answer is "not ready": nodes not up (status), or timing errors (timing check).
constexpr int kExitNotReady = 3;

// Where the stage is (--controller, --endpoints, --config, --as), and the deadline of each call.
struct Connection : stage::StageLocator {
  int timeout_ms = 3000;
};

absl::StatusOr<std::unique_ptr<stage::v1::StageController::Stub>> Connect(const Connection& c, std::string* address) {
  auto resolved = stage::ResolveController(c);
  if (!resolved.ok()) return resolved.status();
  *address = *resolved;
  return stage::v1::StageController::NewStub(stage::MakeChannel(*address));
}

void SetDeadline(grpc::ClientContext* context, const Connection& c) {
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(c.timeout_ms));
}

absl::Status RpcError(const grpc::Status& rpc, const std::string& address) {
  return stage::Annotate(stage::FromGrpcStatus(rpc), absl::StrCat("controller at ", address));
}

std::string ToJson(const google::protobuf::Message& message) { return stage::ToContractJson(message); }

// stagectl status --cameras: every camera node's stream and link statistics (CameraNode.GetStats), asked of the
// nodes at the addresses the controller knows.
int CameraStatus(const Connection& c, const stage::v1::StageStatus& status, bool json) {
  nlohmann::json out = nlohmann::json::array();
  bool all_up = true;
  for (const auto& n : status.nodes()) {
    if (n.kind() != stage::v1::NODE_KIND_CAMERA) continue;
    nlohmann::json j = {{"id", n.id()}, {"backend", n.backend()}, {"address", n.address()}};
    stage::v1::CameraStats stats;
    grpc::Status rpc = grpc::Status(grpc::StatusCode::UNAVAILABLE, "no address");
    if (!n.address().empty()) {
      auto stub = stage::v1::CameraNode::NewStub(stage::MakeChannel(n.address()));
      grpc::ClientContext context;
      SetDeadline(&context, c);
      rpc = stub->GetStats(&context, stage::v1::GetStatsRequest(), &stats);
    }
    if (!rpc.ok()) {
      all_up = false;
      j["error"] = rpc.error_message();
    } else {
      all_up = all_up && stats.link_up();
      j["stats"] = nlohmann::json::parse(ToJson(stats));  // the CameraStats message, in the contract's convention
    }
    out.push_back(std::move(j));
  }
  if (json) {
    std::cout << nlohmann::json{{"cameras", out}}.dump(1) << "\n";
  } else {
    std::cout << absl::StrFormat("%-8s %-7s %-5s %9s %7s %9s %7s %9s %6s %10s  %s\n", "CAMERA", "BACKEND", "LINK",
                                 "FRAMES", "FAILED", "MISSING", "RESENT", "UNDERRUNS", "LOSSES", "RECONNECTS",
                                 "DETAIL");
    for (const auto& j : out) {
      if (j.contains("error")) {
        std::cout << absl::StrFormat("%-8s %-7s %-5s %s\n", j["id"].get<std::string>(), j["backend"].get<std::string>(),
                                     "?", j["error"].get<std::string>());
        continue;
      }
      const auto& s = j["stats"];
      auto n = [&](const char* field) { return std::stoull(s[field].get<std::string>()); };
      std::cout << absl::StrFormat("%-8s %-7s %-5s %9d %7d %9d %7d %9d %6d %10d  %s\n", j["id"].get<std::string>(),
                                   j["backend"].get<std::string>(), s["link_up"].get<bool>() ? "up" : "DOWN",
                                   n("frames_completed"), n("frames_failed"), n("packets_missing"), n("packets_resent"),
                                   n("buffer_underruns"), n("link_losses"), n("reconnects"),
                                   s["link_detail"].get<std::string>());
    }
  }
  return all_up ? 0 : kExitNotReady;
}

// stagectl cameras: the GigE Vision and USB3 Vision cameras this machine's network shows (camera-node --list).
int Cameras(bool json) {
  std::error_code ec;
  const auto self = std::filesystem::read_symlink("/proc/self/exe", ec);
  const std::string program = (ec ? std::filesystem::path(".") : self.parent_path()) / "camera-node";
  std::vector<const char*> argv = {program.c_str(), "--list"};
  if (json) argv.push_back("--json");
  argv.push_back(nullptr);
  std::cout.flush();
  execv(program.c_str(), const_cast<char* const*>(argv.data()));
  return stage::ReportFatal(kProgram, absl::NotFoundError(absl::StrCat(program, ": cannot run it: ", strerror(errno))));
}

int Status(const Connection& c, bool json, bool cameras) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::StageStatus status;
  grpc::Status rpc = (*stub)->GetStageStatus(&context, stage::v1::GetStageStatusRequest(), &status);
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (cameras) return CameraStatus(c, status, json);
  if (json) {
    std::cout << ToJson(status) << "\n";
  } else {
    int64_t now =
        std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch())
            .count();
    std::cout << stage::stagectl::FormatStatusTable(status, now, isatty(STDOUT_FILENO) != 0);
  }
  return status.nodes_up() == status.nodes_total() ? 0 : kExitNotReady;
}

// ---- timing -------------------------------------------------------------------------------------------------------

struct TimingFlags {
  // A rig file to work on locally; empty = ask the controller about the live rig.
  std::string rig;
  std::vector<std::string> overrides;
  bool json = false;
  // export
  std::string vcd_path, svg_path, json_path;
  int64_t frames = 1;
  std::string slots;
  std::string timescale = "1ns";
};

absl::StatusOr<stage::v1::TimingReport> FetchReport(const Connection& c, const TimingFlags& f, std::string* rig_name) {
  stage::v1::TimingQuery query;
  for (const auto& o : f.overrides) query.add_overrides(o);
  if (!f.rig.empty()) {
    std::vector<std::string> errors;
    auto loaded = stage::LoadRig(f.rig, {}, &errors);
    if (!loaded.ok()) {
      // Every error of the file, not the first and a count.
      return errors.size() > 1 ? absl::Status(loaded.status().code(), absl::StrJoin(errors, "\n")) : loaded.status();
    }
    *rig_name = loaded->source_name;
    return stage::timing::CheckTiming(*loaded, query);
  }
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stub.status();
  *rig_name = absl::StrCat("the live rig of the controller at ", address);
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::TimingReport report;
  grpc::Status rpc = (*stub)->CheckTiming(&context, query, &report);
  if (!rpc.ok()) return RpcError(rpc, address);
  return report;
}

std::string WithOverrides(std::string rig_name, const TimingFlags& f) {
  if (!f.overrides.empty()) absl::StrAppend(&rig_name, " with ", absl::StrJoin(f.overrides, ", "));
  return rig_name;
}

int TimingCheck(const Connection& c, const TimingFlags& f) {
  std::string rig_name;
  auto report = FetchReport(c, f, &rig_name);
  if (!report.ok()) return stage::ReportFatal(kProgram, report.status());
  if (f.json) {
    std::cout << ToJson(*report) << "\n";
  } else {
    std::cout << stage::timing::FormatViolations(*report, WithOverrides(rig_name, f));
  }
  return report->errors() > 0 ? kExitNotReady : 0;
}

int TimingShow(const Connection& c, const TimingFlags& f) {
  std::string rig_name;
  auto report = FetchReport(c, f, &rig_name);
  if (!report.ok()) return stage::ReportFatal(kProgram, report.status());
  if (f.json) {
    std::cout << ToJson(report->schedule()) << "\n";
  } else {
    std::cout << stage::timing::FormatScheduleSummary(*report, WithOverrides(rig_name, f));
  }
  return 0;
}

int TimingExport(const Connection& c, const TimingFlags& f) {
  if (f.vcd_path.empty() && f.svg_path.empty() && f.json_path.empty()) {
    std::cerr << kProgram << ": error: timing export needs at least one of --vcd, --svg, --json; see --help\n";
    return 2;
  }
  stage::v1::TimingExportRequest request;
  for (const auto& o : f.overrides) request.add_overrides(o);
  request.set_vcd(!f.vcd_path.empty());
  request.set_svg(!f.svg_path.empty());
  request.set_json(!f.json_path.empty());
  request.set_timescale(f.timescale);
  if (!f.slots.empty()) {
    // A:B, slots A to B-1.
    std::vector<std::string> parts = absl::StrSplit(f.slots, ':');
    int64_t a = 0, b = 0;
    if (parts.size() != 2 || !absl::SimpleAtoi(parts[0], &a) || !absl::SimpleAtoi(parts[1], &b) || a < 0 || b <= a) {
      std::cerr << kProgram << ": error: --slots " << f.slots
                << " is not FIRST:END with 0 <= FIRST < END (slots FIRST to END-1); see --help\n";
      return 2;
    }
    request.set_first_slot(a);
    request.set_slot_count(b - a);
  }
  stage::v1::TimingExport out;
  if (!f.rig.empty()) {
    auto loaded = stage::LoadRig(f.rig);
    if (!loaded.ok()) return stage::ReportFatal(kProgram, loaded.status());
    if (f.slots.empty()) {
      // --frames N: N pattern cycles from slot 0 (the cycle length comes with the report).
      auto report = stage::timing::CheckTiming(*loaded, stage::v1::TimingQuery());
      if (!report.ok()) return stage::ReportFatal(kProgram, report.status());
      request.set_slot_count(f.frames * std::max(1, report->schedule().patterns_size()));
    }
    auto exported = stage::timing::ExportTiming(*loaded, request);
    if (!exported.ok()) return stage::ReportFatal(kProgram, exported.status());
    out = *std::move(exported);
  } else {
    std::string address;
    auto stub = Connect(c, &address);
    if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
    if (f.slots.empty()) {
      grpc::ClientContext context;
      SetDeadline(&context, c);
      stage::v1::TimingReport report;
      grpc::Status rpc = (*stub)->CheckTiming(&context, stage::v1::TimingQuery(), &report);
      if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
      request.set_slot_count(f.frames * std::max(1, report.schedule().patterns_size()));
    }
    grpc::ClientContext context;
    SetDeadline(&context, c);
    grpc::Status rpc = (*stub)->ExportTiming(&context, request, &out);
    if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  }
  for (const auto& [path, text] :
       {std::pair{f.vcd_path, &out.vcd()}, std::pair{f.svg_path, &out.svg()}, std::pair{f.json_path, &out.json()}}) {
    if (path.empty()) continue;
    if (absl::Status s = stage::WriteFileAtomically(path, *text); !s.ok()) return stage::ReportFatal(kProgram, s);
    std::cerr << "wrote " << path << " (" << text->size() << " bytes)\n";
  }
  std::cerr << "schedule " << out.report().schedule().hash() << ", slots " << out.first_slot() << " to "
            << out.first_slot() + out.slot_count() - 1 << ": " << out.report().errors() << " error(s), "
            << out.report().warnings() << " warning(s)\n";
  return 0;
}

int TimingRehearse(const Connection& c, int64_t slots, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  // The rehearsal takes as long as its slots, plus the start and the reports.
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(c.timeout_ms) +
                       std::chrono::seconds(5 + slots / 100));
  stage::v1::RehearseTriggersRequest request;
  request.set_slot_count(slots);
  stage::v1::TriggerRehearsal rehearsal;
  grpc::Status rpc = (*stub)->RehearseTriggers(&context, request, &rehearsal);
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (json) {
    std::cout << ToJson(rehearsal) << "\n";
  } else {
    std::cout << absl::StrFormat("trigger rehearsal: %d slots, sent %.3f ms ahead, through the controller at %s\n",
                                 rehearsal.slot_count(), rehearsal.lead_ns() / 1e6, address);
    std::cout << absl::StrFormat("%-10s %9s %9s %7s %7s %12s %12s %13s %s\n", "CAMERA", "TRIGGERS", "FIRED", "LATE",
                                 "MISSED", "MIN LEAD", "MEDIAN LEAD", "CLOCK OFFSET", "NOTE");
    for (const auto& cam : rehearsal.cameras()) {
      const auto& r = cam.report();
      std::string note = cam.error().empty() ? r.warning() : cam.error();
      if (note.empty() && r.late_slots_size() + r.missed_slots_size() > 0) {
        note = absl::StrCat("first late/missed slot ",
                            std::min(r.late_slots_size() > 0 ? r.late_slots(0) : INT64_MAX,
                                     r.missed_slots_size() > 0 ? r.missed_slots(0) : INT64_MAX));
      }
      std::cout << absl::StrFormat("%-10s %9d %9d %7d %7d %9.3f ms %9.3f ms %10.1f us %s\n", cam.camera_id(),
                                   r.received(), r.fired(), r.late(), r.missed(), r.min_lead_ns() / 1e6,
                                   r.median_lead_ns() / 1e6, cam.clock().offset_ns() / 1e3, note);
    }
  }
  for (const auto& cam : rehearsal.cameras()) {
    if (!cam.error().empty() || cam.report().late() + cam.report().missed() > 0) return kExitNotReady;
  }
  return 0;
}

// Exit codes of `stagectl capture`: 0 COMPLETE; 4 DEGRADED (frames lost or the self-test failed); 1 FAILED.
constexpr int kExitDegraded = 4;

std::string Counts(const stage::v1::LedgerCounts& c) {
  std::string out = absl::StrFormat("%d of %d stored", c.stored(), c.expected());
  std::vector<std::string> lost;
  for (const auto& l : c.lost()) {
    lost.push_back(absl::StrCat(l.frames(), " ", stage::LossReasonName(l.reason())));
  }
  if (!lost.empty()) absl::StrAppend(&out, " (", absl::StrJoin(lost, ", "), ")");
  return out;
}

void PrintSummary(const stage::v1::TakeSummary& t) {
  std::cout << "take " << t.take_id() << (t.name().empty() ? "" : " (" + t.name() + ")") << ": "
            << stage::TakeOutcomeName(t.outcome()) << "\n  " << t.frames() << " frames, " << t.slots() << " slots, "
            << absl::StrFormat("%.1f MB", static_cast<double>(t.bytes()) / 1e6) << " in " << t.dir() << "\n"
            << "  ledger: " << Counts(t.total()) << "\n";
  std::map<std::string, stage::v1::LedgerCounts> by_role;
  for (const auto& c : t.cameras()) {
    stage::AddCounts(c.counts(), &by_role[stage::CameraRoleName(c.role())]);
  }
  for (const auto& [role, counts] : by_role) std::cout << "    " << role << ": " << Counts(counts) << "\n";
  for (const auto& c : t.cameras()) {
    if (c.counts().stored() < c.counts().expected() || !c.error().empty()) {
      std::cout << "    " << c.camera_id() << ": " << Counts(c.counts()) << (c.error().empty() ? "" : "; " + c.error())
                << "\n";
    }
  }
  for (const auto& a : t.alignment()) std::cout << "  self-test " << a.camera_id() << ": " << a.message() << "\n";
  if (t.total().paused() > 0) {
    std::vector<std::string> gaps;
    for (const auto& g : t.paused()) gaps.push_back(absl::StrCat(g.first(), "-", g.end() - 1));
    std::cout << "  paused over slots " << absl::StrJoin(gaps, ", ") << " (" << t.total().paused()
              << " camera slots, not lost)\n";
  }
  if (!t.ground_truth_dir().empty()) std::cout << "  ground truth (simulated stage): " << t.ground_truth_dir() << "\n";
  if (!t.hint().empty()) std::cout << "  " << t.hint() << "\n";
}

// The ledger as a camera x pattern grid, cameras that lost frames only: '.' nothing lost, 1-9 frames lost, '+' more.
void PrintGrid(const stage::v1::TakeSummary& t) {
  size_t patterns = 0;
  std::vector<const stage::v1::CameraTakeSummary*> lossy;
  for (const auto& c : t.cameras()) {
    patterns = std::max(patterns, static_cast<size_t>(c.lost_by_pattern_size()));
    bool lost = false;
    for (int64_t n : c.lost_by_pattern()) lost = lost || n > 0;
    if (lost) lossy.push_back(&c);
  }
  if (lossy.empty()) {
    std::cout << "  no frame lost (" << t.cameras_size() << " cameras)\n";
    return;
  }
  std::string ruler;
  for (size_t p = 0; p < patterns; ++p) ruler += p % 10 == 0 ? static_cast<char>('0' + (p / 10) % 10) : ' ';
  std::cout << "  frames lost by camera x pattern (" << lossy.size() << " of " << t.cameras_size()
            << " cameras lost any):\n"
            << absl::StrFormat("    %-10s %s\n", "pattern", ruler);
  for (const auto* c : lossy) {
    std::string row;
    for (int64_t n : c->lost_by_pattern()) row += n == 0 ? '.' : n > 9 ? '+' : static_cast<char>('0' + n);
    std::cout << absl::StrFormat("    %-10s %s\n", c->camera_id(), row);
  }
}

// Shows a take's events (Capture, Arm, WatchTake) on stderr as they come: states, messages, a progress line. Returns
// the summary, if one came, and the stream's end.
struct TakeStream {
  std::optional<stage::v1::TakeSummary> summary;
  grpc::Status status;
};
TakeStream ShowTakeEvents(grpc::ClientReader<stage::v1::CaptureEvent>& reader) {
  stage::v1::CaptureEvent event;
  TakeStream out;
  const bool tty = isatty(STDERR_FILENO) != 0;
  auto last_line = std::chrono::steady_clock::now() - std::chrono::seconds(10);
  while (reader.Read(&event)) {
    if (event.has_state()) {
      if (tty) std::cerr << "\n";
      std::cerr << "session: " << stage::SessionStateName(event.state()) << std::endl;
    } else if (event.has_message()) {
      if (tty) std::cerr << "\n";
      std::cerr << event.message() << std::endl;
    } else if (event.has_progress()) {
      const auto& p = event.progress();
      if (p.phase() == stage::v1::CAPTURE_PHASE_DONE) continue;  // the summary follows
      const auto now = std::chrono::steady_clock::now();
      if (!tty && now - last_line < std::chrono::seconds(2)) continue;
      last_line = now;
      std::string groups;
      for (const auto& r : p.roles()) {
        absl::StrAppend(&groups, "  ", stage::CameraRoleName(r.role()), " ", r.received(), "/", r.expected());
        if (r.lost() > 0) absl::StrAppend(&groups, " (", r.lost(), " lost)");
      }
      if (p.phase() == stage::v1::CAPTURE_PHASE_OFFLOADING) {
        // Burst cameras write what they held after the take.
        std::cerr << (tty ? "\r" : "")
                  << absl::StrFormat("offloading: %d/%d frames written", p.frames_written(), p.frames_expected())
                  << (tty ? "" : "\n") << std::flush;
        continue;
      }
      const double frac = p.frames_expected() > 0 ? static_cast<double>(p.frames_received()) / p.frames_expected() : 0;
      const int bar = static_cast<int>(frac * 30);
      // What the take waits for (cameras still rendering or reading out, the slot clock): on a terminal, cut to fit
      // one line.
      std::string waiting = p.waiting_for().empty() ? "" : absl::StrCat("  waiting for ", p.waiting_for());
      if (tty && waiting.size() > 70) waiting = waiting.substr(0, 67) + "...";
      std::cerr << (tty ? "\r" : "") << (p.phase() == stage::v1::CAPTURE_PHASE_PAUSED ? "paused " : "") << "["
                << std::string(static_cast<size_t>(bar), '#') << std::string(static_cast<size_t>(30 - bar), '.') << "] "
                << absl::StrFormat("%3.0f%% %d/%d frames, %.1f s", 100 * frac, p.frames_received(), p.frames_expected(),
                                   p.elapsed_s())
                << groups << waiting << (tty ? "\033[K" : "\n") << std::flush;
    } else if (event.has_summary()) {
      out.summary = event.summary();
    }
  }
  if (tty) std::cerr << "\n";
  out.status = reader.Finish();
  return out;
}

// The take's verdict on stdout (or JSON) and as the exit code: 0 COMPLETE, 4 DEGRADED, 1 FAILED.
int Verdict(const stage::v1::TakeSummary& summary, bool json) {
  if (json) {
    std::cout << ToJson(summary) << "\n";
  } else {
    PrintSummary(summary);
  }
  if (summary.outcome() == stage::v1::TAKE_OUTCOME_COMPLETE) return 0;
  return summary.outcome() == stage::v1::TAKE_OUTCOME_DEGRADED ? kExitDegraded : 1;
}

// Capture (or Arm, `arm_only`): shows the session's events on stderr and the take's summary on stdout.
// --ground-truth's words.
const std::map<std::string, stage::v1::GroundTruthScope> kGroundTruthScopes = {
    {"full", stage::v1::GROUND_TRUTH_SCOPE_FULL},
    {"scene", stage::v1::GROUND_TRUTH_SCOPE_SCENE},
    {"none", stage::v1::GROUND_TRUTH_SCOPE_NONE}};

// Capture (or Arm, `arm_only`) with the session's events shown on stderr: the take's summary.
absl::StatusOr<stage::v1::TakeSummary> RecordTake(const Connection& c, const stage::v1::CaptureRequest& request,
                                                  bool arm_only) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stub.status();
  grpc::ClientContext context;  // no deadline: a take lasts as long as it lasts
  auto reader = arm_only ? (*stub)->Arm(&context, request) : (*stub)->Capture(&context, request);
  TakeStream stream = ShowTakeEvents(*reader);
  if (!stream.status.ok()) return RpcError(stream.status, address);
  if (!stream.summary) return absl::DataLossError("the take ended without a summary");
  return *stream.summary;
}

int Capture(const Connection& c, int64_t frames, double seconds, const std::string& name, bool json,
            bool arm_only = false, stage::v1::GroundTruthScope ground_truth = stage::v1::GROUND_TRUTH_SCOPE_FULL) {
  stage::v1::CaptureRequest request;
  request.set_frames(frames);
  request.set_seconds(seconds);
  request.set_name(name);
  request.set_ground_truth(ground_truth);
  auto recorded = RecordTake(c, request, arm_only);
  if (!recorded.ok()) return stage::ReportFatal(kProgram, recorded.status());
  const stage::v1::TakeSummary& summary = *recorded;
  if (arm_only) {
    if (json) {
      std::cout << ToJson(summary) << "\n";
    } else {
      std::cout << "take " << summary.take_id() << " armed: " << summary.frames() << " frames into " << summary.dir()
                << "\n  `stagectl capture` starts it, `stagectl abort` drops it\n";
    }
    return 0;
  }
  return Verdict(summary, json);
}

// Follows a running take (the session's, or `take_id`) to its end, as `capture` shows it; a take that has ended gives
// its summary at once. The verdict is the exit code, as for capture.
int Watch(const Connection& c, const std::string& take_id, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  stage::v1::WatchTakeRequest request;
  request.set_take_id(take_id);
  auto reader = (*stub)->WatchTake(&context, request);
  TakeStream stream = ShowTakeEvents(*reader);
  if (!stream.status.ok()) return stage::ReportFatal(kProgram, RpcError(stream.status, address));
  if (!stream.summary) return stage::ReportFatal(kProgram, absl::DataLossError("the take ended without a summary"));
  return Verdict(*stream.summary, json);
}

// A take's ledger, every page: a line per entry (camera, slot, pattern, what became of it), or JSON lines.
int Ledger(const Connection& c, const std::string& take_id, const std::string& camera, bool lost_only, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  stage::v1::GetLedgerRequest request;
  request.set_take_id(take_id);
  request.set_camera_id(camera);
  request.set_lost_only(lost_only);
  int64_t shown = 0, total = 0;
  std::string id = take_id;
  do {
    grpc::ClientContext context;
    SetDeadline(&context, c);
    stage::v1::LedgerPage page;
    grpc::Status rpc = (*stub)->GetLedger(&context, request, &page);
    if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
    id = page.take_id();
    total = page.total();
    for (const auto& e : page.entries()) {
      if (json) {
        std::cout << ToJson(e) << "\n";
      } else {
        std::cout << absl::StrFormat("%-10s %8d %4d  %-14s %s\n", e.camera_id(), e.slot(), e.pattern(),
                                     stage::LossReasonName(e.reason()), e.detail());
      }
    }
    shown += page.entries_size();
    request.set_page_token(page.next_page_token());
  } while (!request.page_token().empty());
  if (!json) std::cerr << shown << " of " << total << " entries of take " << id << "\n";
  return 0;
}

// Pause, resume or abort the session's take.
int Session(const Connection& c, const std::string& what, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::SessionReply reply;
  stage::v1::SessionRequest request;
  grpc::Status rpc = what == "pause"    ? (*stub)->Pause(&context, request, &reply)
                     : what == "resume" ? (*stub)->Resume(&context, request, &reply)
                                        : (*stub)->Abort(&context, request, &reply);
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (json) {
    std::cout << ToJson(reply) << "\n";
  } else {
    std::cout << reply.message() << "\n";
  }
  return 0;
}

// The emergency stop, or its reset. Exit 3 when a light node did not confirm.
int EStop(const Connection& c, const std::string& reason, bool reset, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::EmergencyStopReply reply;
  grpc::Status rpc;
  if (reset) {
    rpc = (*stub)->ResetEmergencyStop(&context, stage::v1::ResetEmergencyStopRequest(), &reply);
  } else {
    stage::v1::EmergencyStopRequest request;
    request.set_reason(reason.empty() ? "stagectl estop" : reason);
    rpc = (*stub)->EmergencyStop(&context, request, &reply);
  }
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (json) {
    std::cout << ToJson(reply) << "\n";
  } else {
    int ok = 0;
    for (const auto& n : reply.nodes()) {
      ok += n.dark() ? 1 : 0;
      std::cout << fmt::format("  {:<20} {:<14} {:8.2f} ms  {}\n", n.node_id(),
                               n.dark() ? (reset ? "reset" : "dark") : (reset ? "STILL LATCHED" : "NOT CONFIRMED"),
                               n.ms(), n.error());
    }
    if (reset) {
      std::cout << "emergency stop reset: " << ok << " of " << reply.nodes_size() << " light nodes out of blackout\n";
    } else {
      std::cout << fmt::format("emergency stop latched: {} of {} light nodes confirmed dark in {:.2f} ms{}\n", ok,
                               reply.nodes_size(), reply.elapsed_ms(),
                               reply.all_dark() ? "" : "; CHECK THE OTHERS BY HAND (their lights may be on)");
    }
  }
  return reply.all_dark() ? 0 : 3;
}

// A camera's latest preview, written as PNG.
int Preview(const Connection& c, const std::string& camera, const std::string& out, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::ControllerPreviewRequest request;
  request.set_camera_id(camera);
  stage::v1::Preview preview;
  grpc::Status rpc = (*stub)->GetPreview(&context, request, &preview);
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  const std::string path = out.empty() ? camera + "-preview.png" : out;
  if (absl::Status s = stage::WriteFileAtomically(path, preview.png()); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (json) {
    stage::v1::Preview meta = preview;
    meta.clear_png();
    std::cout << ToJson(meta) << "\n";
  } else {
    std::cout << camera << ": " << preview.width() << "x" << preview.height() << " preview of take "
              << preview.frame().take_id() << " slot " << preview.frame().slot() << " -> " << path << "\n";
  }
  return 0;
}

struct ProcessFlags {
  std::string take_id, stage = "graph", frames = "0:", cameras, geometry, calibration, worker;
  // --stage graph (the processing graph): the outputs asked for, frames per task, each stage's own flags
  // (STAGE:FLAG), retries of a failed task, tasks at a time.
  std::string graph_stages;
  int64_t chunk_frames = 0;
  std::vector<std::string> with;
  int32_t retries = -1, jobs = 0;  // retries -1: not given (the graph's default, 1)
  std::string stabilize_method;    // empty: the worker's default (the flow)
  int32_t texture_size = 0;        // 0: the worker's default
  // The asset's stages (0 and empty: the worker's defaults).
  std::string asset_source, network, held_out_cameras;
  int32_t iterations = 0, batch = 0, input_size = 0, levels = 0, geometry_size = 0, image_size = 0, frame_step = 0;
  double region_weight = 0, map_loss = 0, learning_rate = 0, crop_mm = 0;
  bool json = false;
};

// A flag's value as the suffix of its enum's value names: "asset-train" -> "ASSET_TRAIN".
std::string EnumSuffix(absl::string_view value) {
  std::string name = absl::AsciiStrToUpper(value);
  absl::StrReplaceAll({{"-", "_"}}, &name);
  return name;
}

// The asset's options of `f`, set on `request` only when one is given (the worker refuses options a stage does not
// take, and an asset message at all with --stage asset-infer).
absl::Status SetAssetOptions(const ProcessFlags& f, stage::v1::ProcessTakeRequest* request) {
  stage::v1::AssetOptions a;
  if (!f.asset_source.empty()) {
    a.set_source(f.asset_source == "truth" ? stage::v1::ASSET_SOURCE_TRUTH : stage::v1::ASSET_SOURCE_RECONSTRUCTION);
  }
  if (!f.network.empty()) {
    stage::v1::AssetNetwork network;
    if (!stage::v1::AssetNetwork_Parse("ASSET_NETWORK_" + EnumSuffix(f.network), &network) ||
        network == stage::v1::ASSET_NETWORK_UNSPECIFIED) {
      return absl::InvalidArgumentError(absl::StrCat("--network: \"", f.network, "\" is not a network of the asset"));
    }
    a.set_network(network);
  }
  for (absl::string_view id : absl::StrSplit(f.held_out_cameras, ',', absl::SkipEmpty())) {
    a.add_held_out_cameras(std::string(id));
  }
  a.set_iterations(f.iterations);
  a.set_batch(f.batch);
  a.set_input_size(f.input_size);
  a.set_levels(f.levels);
  a.set_geometry_size(f.geometry_size);
  a.set_image_size(f.image_size);
  a.set_region_weight(f.region_weight);
  a.set_map_loss(f.map_loss);
  a.set_learning_rate(f.learning_rate);
  a.set_frame_step(f.frame_step);
  a.set_crop_mm(f.crop_mm);
  if (a.ByteSizeLong() > 0) *request->mutable_asset() = a;
  return absl::OkStatus();
}

// The graph's options of `f` on `request` with --stage graph; refused with another stage.
absl::Status SetGraphRequest(const ProcessFlags& f, stage::v1::ProcessingStage kind,
                             stage::v1::ProcessTakeRequest* request) {
  if (kind != stage::v1::PROCESSING_STAGE_GRAPH) {
    if (!f.graph_stages.empty() || f.chunk_frames != 0 || !f.with.empty() || f.jobs != 0 || f.retries >= 0) {
      return absl::InvalidArgumentError(
          "--stages, --chunk-frames, --with, --retries and --jobs apply to --stage graph");
    }
    return absl::OkStatus();
  }
  stage::v1::GraphRequest* g = request->mutable_graph();
  for (absl::string_view word : absl::StrSplit(f.graph_stages, ',', absl::SkipEmpty())) {
    const auto s = stage::ParseProcessingStage(word);
    if (!s) return absl::InvalidArgumentError(absl::StrCat("--stages: \"", word, "\" is not a stage"));
    g->add_stages(*s);
  }
  for (const std::string& w : f.with) {
    const size_t colon = w.find(':');
    const auto s = colon == std::string::npos ? std::nullopt : stage::ParseProcessingStage(w.substr(0, colon));
    if (!s) {
      return absl::InvalidArgumentError(
          absl::StrCat("--with ", w, ": expected STAGE:FLAG (e.g. mvs:--image-scale=0.5)"));
    }
    stage::v1::StageFlags* flags = g->add_flags();
    flags->set_stage(*s);
    flags->add_args(w.substr(colon + 1));
  }
  g->set_chunk_frames(f.chunk_frames);
  g->set_retries(f.retries < 0 ? 1 : f.retries);
  g->set_jobs(f.jobs);
  return absl::OkStatus();
}

// A processing stage over a take on one of the stage's workers, with a progress bar; no deadline (it takes as long as
// the work), Ctrl-C cancels it on the worker.
int Process(const Connection& c, const ProcessFlags& f) {
  stage::v1::ProcessTakeRequest request;
  request.set_take_id(f.take_id);
  const auto parsed = stage::ParseProcessingStage(f.stage);
  if (!parsed) {
    return stage::ReportFatal(kProgram, absl::InvalidArgumentError(absl::StrCat(
                                            "--stage: \"", f.stage,
                                            "\" is not a stage (graph, photometric, calibration, mvs, fit, textures, "
                                            "stabilize, asset-dataset, asset-train, asset-infer)")));
  }
  const stage::v1::ProcessingStage kind = *parsed;
  if (auto s = SetAssetOptions(f, &request); !s.ok()) return stage::ReportFatal(kProgram, s);
  if (auto s = SetGraphRequest(f, kind, &request); !s.ok()) return stage::ReportFatal(kProgram, s);
  request.set_stage(kind);
  int64_t first = 0, last = -1;
  if (auto s = stage::ParseFrameRange("--frames", f.frames, &first, &last); !s.ok()) {
    return stage::ReportFatal(kProgram, s);
  }
  request.set_first_frame(first);
  request.set_last_frame(last < 0 ? 0 : last);
  for (absl::string_view id : absl::StrSplit(f.cameras, ',', absl::SkipEmpty())) request.add_cameras(std::string(id));
  if (f.geometry == "none") {
    request.set_geometry_source(stage::v1::GEOMETRY_SOURCE_NONE);
  } else if (f.geometry == "mvs") {
    request.set_geometry_source(stage::v1::GEOMETRY_SOURCE_MVS);
  } else if (!f.geometry.empty()) {
    request.set_geometry_source(stage::v1::GEOMETRY_SOURCE_DIRECTORY);
    request.set_geometry(f.geometry);
  }
  request.set_calibration(f.calibration);
  request.set_texture_size(f.texture_size);
  if (f.stabilize_method == "flow") request.set_stabilize_method(stage::v1::STABILIZE_METHOD_FLOW);
  if (f.stabilize_method == "unet") request.set_stabilize_method(stage::v1::STABILIZE_METHOD_UNET);
  request.set_worker_id(f.worker);
  // The flags are checked before the stage is looked for: a bad one is named whether or not the stage is up.
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  auto reader = (*stub)->ProcessTake(&context, request);
  stage::v1::ProcessingProgress progress, last_message;
  stage::ProgressLine bar(
      kind == stage::v1::PROCESSING_STAGE_GRAPH         ? "units"
      : kind == stage::v1::PROCESSING_STAGE_CALIBRATION ? "cameras"
      : kind == stage::v1::PROCESSING_STAGE_ASSET_TRAIN ? "steps"
      : kind == stage::v1::PROCESSING_STAGE_MVS || kind == stage::v1::PROCESSING_STAGE_FIT ||
              kind == stage::v1::PROCESSING_STAGE_TEXTURES || kind == stage::v1::PROCESSING_STAGE_STABILIZE ||
              kind == stage::v1::PROCESSING_STAGE_ASSET_DATASET || kind == stage::v1::PROCESSING_STAGE_ASSET_INFER
          ? "frames"
          : "camera frames");
  while (reader->Read(&progress)) {
    if (progress.finished()) {
      last_message = progress;
    } else if (progress.frames_done() == 0) {
      bar.Message(progress.message());
    } else {
      bar.Update(progress.frames_done(), progress.frames_total(), progress.message());
    }
  }
  bar.Finish();
  grpc::Status rpc = reader->Finish();
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (!last_message.finished()) {
    return stage::ReportFatal(kProgram, absl::DataLossError("the worker ended without saying where the results are"));
  }
  if (f.json) {
    std::cout << ToJson(last_message) << "\n";
  } else {
    std::cout << last_message.message() << "\n";
  }
  return 0;
}

struct CalibrateFlags {
  double seconds = 5;
  std::string name = "calibration", worker;
  bool json = false;
  std::string ground_truth = "scene";  // a key of kGroundTruthScopes
};

// Records a calibration take (the ChArUco board moved through the stage's volume) and runs the calibration stage on
// it on one of the stage's workers: the take's summary, then the calibration's report (docs/geometry.md).
int Calibrate(const Connection& c, const CalibrateFlags& f) {
  stage::v1::CaptureRequest request;
  request.set_seconds(f.seconds);
  request.set_name(f.name);
  request.set_ground_truth(kGroundTruthScopes.at(f.ground_truth));
  auto recorded = RecordTake(c, request, /*arm_only=*/false);
  if (!recorded.ok()) return stage::ReportFatal(kProgram, recorded.status());
  const stage::v1::TakeSummary& summary = *recorded;
  if (!f.json) PrintSummary(summary);
  if (summary.outcome() == stage::v1::TAKE_OUTCOME_FAILED) {
    return stage::ReportFatal(kProgram, absl::AbortedError(absl::StrCat("the calibration take ", summary.take_id(),
                                                                        " failed: nothing to calibrate from")));
  }
  ProcessFlags p;
  p.take_id = summary.take_id();
  p.stage = "calibration";
  p.worker = f.worker;
  p.json = f.json;
  return Process(c, p);
}

// A take's processing graph status in words: "mvs done 2/2, photometric failed 1/2, ...".
std::string ProcessingWords(const stage::v1::TakeRecord& t) {
  std::vector<std::string> words;
  for (const auto& p : t.processing()) {
    const std::string stage = stage::v1::ProcessingStage_Name(p.stage());
    const std::string state = stage::v1::StageProcessingState_Name(p.state());
    words.push_back(absl::AsciiStrToLower(absl::StrCat(absl::StripPrefix(stage, "PROCESSING_STAGE_"), " ",
                                                       absl::StripPrefix(state, "STAGE_PROCESSING_STATE_"), " ",
                                                       p.up_to_date(), "/", p.units())));
  }
  return absl::StrJoin(words, ", ");
}

int Takes(const Connection& c, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::TakeList list;
  grpc::Status rpc = (*stub)->ListTakes(&context, stage::v1::ListTakesRequest(), &list);
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (json) {
    std::cout << ToJson(list) << "\n";
    return 0;
  }
  std::cout << absl::StrFormat("%-24s %-10s %-9s %8s %14s %10s  %s\n", "TAKE", "STATE", "OUTCOME", "SECONDS", "FRAMES",
                               "MB", "NAME");
  for (const auto& t : list.takes()) {
    std::cout << absl::StrFormat("%-24s %-10s %-9s %8.2f %14s %10.1f  %s\n", t.id(), stage::TakeStateName(t.state()),
                                 stage::TakeOutcomeName(t.outcome()), t.duration_s(),
                                 absl::StrCat(t.frames_stored(), "/", t.frames_expected()),
                                 static_cast<double>(t.size_bytes()) / 1e6, t.name());
    if (t.processing_size() > 0) std::cout << "    processing: " << ProcessingWords(t) << "\n";
  }
  std::cout << list.takes_size() << " take(s) in " << list.take_root() << "\n";
  return 0;
}

int TakeShow(const Connection& c, const std::string& id, bool json) {
  std::string address;
  auto stub = Connect(c, &address);
  if (!stub.ok()) return stage::ReportFatal(kProgram, stub.status());
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::GetTakeRequest request;
  request.set_take_id(id);
  stage::v1::TakeSummary take;
  grpc::Status rpc = (*stub)->GetTake(&context, request, &take);
  if (!rpc.ok()) return stage::ReportFatal(kProgram, RpcError(rpc, address));
  if (json) {
    std::cout << ToJson(take) << "\n";
  } else {
    PrintSummary(take);
    PrintGrid(take);
  }
  return 0;
}

struct FaultFlags {
  std::string world;
  std::string target;
  bool dead = false, alive = false;
  std::optional<double> delay_us, miss_triggers, drop_frames, clock_offset_us, clock_drift_ppm, crash_at_s;
  std::optional<int> extra_steps;
  std::vector<int64_t> drop_slots;
};

// Injects a fault into the running simulated stage's world (docs/simulator.md#faults).
int SimFault(const Connection& c, const FaultFlags& f) {
  std::string address = f.world;
  if (address.empty()) {
    auto endpoints = stage::ReadSimEndpoints(c, "simulated world");
    if (!endpoints.ok()) return stage::ReportFatal(kProgram, endpoints.status());
    if (endpoints->world().empty()) {
      return stage::ReportFatal(
          kProgram, absl::FailedPreconditionError("the simulated stage runs without a world (stage-sim --world none)"));
    }
    address = endpoints->world();
  }
  stage::v1::SimFault fault;
  fault.set_target(f.target);
  fault.set_dead(f.dead);
  if (f.delay_us) fault.set_delay_us(*f.delay_us);
  if (f.miss_triggers) fault.set_miss_triggers(*f.miss_triggers);
  if (f.drop_frames) fault.set_drop_frames(*f.drop_frames);
  if (f.clock_offset_us) fault.set_clock_offset_us(*f.clock_offset_us);
  if (f.clock_drift_ppm) fault.set_clock_drift_ppm(*f.clock_drift_ppm);
  if (f.crash_at_s) fault.set_crash_at_s(*f.crash_at_s);
  if (f.extra_steps) fault.set_extra_steps(*f.extra_steps);
  for (int64_t k : f.drop_slots) fault.add_drop_slots(k);
  auto stub = stage::v1::SimWorld::NewStub(stage::MakeChannel(address));
  grpc::ClientContext context;
  SetDeadline(&context, c);
  stage::v1::WorldAck ack;
  grpc::Status rpc = stub->InjectFault(&context, fault, &ack);
  if (!rpc.ok()) {
    return stage::ReportFatal(kProgram,
                              stage::Annotate(stage::FromGrpcStatus(rpc), absl::StrCat("world at ", address)));
  }
  std::cout << "injected: " << fault.ShortDebugString() << "\n";
  return 0;
}

void AddTimingFlags(CLI::App* cmd, TimingFlags* f) {
  cmd->add_option("--rig", f->rig,
                  "Work on this rig file (or builtin:fastage) here instead of asking the controller about the live "
                  "rig");
  cmd->add_option("--set", f->overrides,
                  "What-if: override a rig field, PATH=VALUE (repeatable), e.g. timing.led_switch_delay_us=60 or "
                  "cameras[hs-1].exposure_us=850")
      ->expected(1)
      ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Command-line console of the FaStage stage. Exit codes: 0 ok, 1 failure, 2 bad usage, "
      "3 not ready (status: nodes not up; timing check: the schedule has errors).",
      "stagectl"};
  app.set_version_flag("--version", std::string("stagectl (FaStage) ") + std::string(stage::kVersion));
  Connection c;
  std::string log_level;
  app.add_option("--controller", c.controller,
                 "Controller address host:port (default: $FASTAGE_CONTROLLER or the "
                 "stage-sim endpoint file)");
  app.add_option("--config", c.rig_path, "Rig file: talk to the controller at its controller.listen address");
  app.add_option(
      "--endpoints", c.endpoints,
      "stage-sim endpoint file (default: $FASTAGE_ENDPOINTS or " + stage::DefaultSimRunDir() + "/endpoints.json)");
  app.add_option("--timeout-ms", c.timeout_ms, "Deadline of each call to the controller")->check(CLI::Range(1, 600000));
  app.add_option("--as", c.identity,
                 "Identity to present when the rig says mutual TLS: operator/NAME or observer/NAME, whose certificate "
                 "and key are in the rig's security.cert_dir (default: $FASTAGE_IDENTITY, else operator/$USER)");
  app.add_option("--log-level", log_level, "Log levels (spdlog syntax)");
  app.require_subcommand(1);
  bool json = false;
  CLI::App* status = app.add_subcommand("status", "Show every node of the stage: state, address, version, RTT");
  status->add_flag("--json", json, "Print JSON for scripts instead of the table");
  bool status_cameras = false;
  status->add_flag("--cameras", status_cameras,
                   "Each camera's stream and link statistics instead (frames, failures, missing and resent packets, "
                   "underruns, link losses and reconnects; docs/cameras.md#statistics)");
  CLI::App* cameras = app.add_subcommand(
      "cameras",
      "List the GigE Vision and USB3 Vision cameras this machine sees (Aravis discovery: camera-node --list)");
  cameras->add_flag("--json", json, "Print JSON for scripts instead of the table");

  TimingFlags tf;
  CLI::App* timing = app.add_subcommand(
      "timing", "The timing schedule: verify it (with what-if overrides), show it per device, export waveforms");
  timing->require_subcommand(1);
  CLI::App* check = timing->add_subcommand(
      "check", "Dry-run the verifier on the live rig (or --rig FILE) with --set overrides; exit 3 if it has errors");
  AddTimingFlags(check, &tf);
  check->add_flag("--json", tf.json, "Print the report (violations, figures, schedule) as JSON");
  CLI::App* show = timing->add_subcommand("show", "Summarize the schedule per light node and camera");
  AddTimingFlags(show, &tf);
  show->add_flag("--json", tf.json, "Print the compiled schedule as JSON");
  CLI::App* exporter = timing->add_subcommand(
      "export", "Write the schedule as VCD (GTKWave, PulseView, sigrok-cli), an SVG timing diagram and JSON");
  AddTimingFlags(exporter, &tf);
  exporter->add_option("--vcd", tf.vcd_path, "Write a VCD (IEEE 1364) file here");
  exporter->add_option("--svg", tf.svg_path, "Write an SVG timing diagram here");
  exporter->add_option("--json", tf.json_path, "Write the report and the window's slots as JSON here");
  exporter->add_option("--frames", tf.frames, "Export this many pattern cycles (frames) from slot 0")
      ->check(CLI::Range(int64_t{1}, int64_t{2000}))
      ->capture_default_str();
  exporter->add_option("--slots", tf.slots, "Export slots FIRST to END-1 instead (FIRST:END)");
  exporter->add_option("--timescale", tf.timescale, "VCD timescale: 1, 10 or 100 of fs, ps, ns, us, ms, s")
      ->capture_default_str();

  int64_t rehearse_slots = 912;
  bool rehearse_json = false;
  CLI::App* rehearse = timing->add_subcommand(
      "rehearse",
      "Stream scheduled software triggers to the live stage's scheduled-software cameras and report what fired, "
      "late or missed (nothing is recorded); exit 3 if any trigger was not fired");
  rehearse->add_option("--slots", rehearse_slots, "Slots to rehearse")
      ->capture_default_str()
      ->check(CLI::Range(1, 91200));
  rehearse->add_flag("--json", rehearse_json, "Print the nodes' reports as JSON");

  int64_t capture_frames = 0;
  double capture_seconds = 0;
  std::string capture_name;
  bool capture_json = false;
  CLI::App* capture = app.add_subcommand(
      "capture",
      "Capture a take: arm every node, run the slot clock for the frames asked, record, and print the ledger's "
      "verdict. Exit codes: 0 COMPLETE, 4 DEGRADED (frames lost or the alignment self-test failed), 1 FAILED");
  auto* frames_opt = capture->add_option("--frames", capture_frames, "Frames (cycles of the pattern set) to capture")
                         ->check(CLI::Range(int64_t{1}, int64_t{1} << 30));
  auto* seconds_opt =
      capture->add_option("--seconds", capture_seconds, "Seconds of the stage to capture (rounded up to frames)")
          ->check(CLI::PositiveNumber);
  frames_opt->excludes(seconds_opt);
  capture->add_option("--name", capture_name, "The take's name in the catalog");
  capture->add_flag("--json", capture_json, "Print the take's summary as JSON (progress still goes to stderr)");
  std::string capture_truth = "full";
  auto* truth_opt = capture
                        ->add_option("--ground-truth", capture_truth,
                                     "Simulated stage: how much of the world's ground truth goes into the take's "
                                     "directory: full, scene (cameras and subject, no per-camera maps) or none")
                        ->check(CLI::IsMember(kGroundTruthScopes))
                        ->capture_default_str();
  bool no_ground_truth = false;
  capture->add_flag("--no-ground-truth", no_ground_truth, "Simulated stage: the same as --ground-truth none")
      ->excludes(truth_opt);
  int64_t arm_frames = 0;
  double arm_seconds = 0;
  std::string arm_name;
  bool arm_json = false;
  CLI::App* arm = app.add_subcommand(
      "arm", "Arm a take and leave it armed: every node gets its table or plan now; `stagectl capture` starts it");
  auto* arm_frames_opt = arm->add_option("--frames", arm_frames, "Frames (cycles of the pattern set) to capture")
                             ->check(CLI::Range(int64_t{1}, int64_t{1} << 30));
  auto* arm_seconds_opt =
      arm->add_option("--seconds", arm_seconds, "Seconds of the stage to capture (rounded up to frames)")
          ->check(CLI::PositiveNumber);
  arm_frames_opt->excludes(arm_seconds_opt);
  arm->add_option("--name", arm_name, "The take's name in the catalog");
  arm->add_flag("--json", arm_json, "Print the armed take as JSON");
  bool session_json = false;
  CLI::App* pause = app.add_subcommand("pause", "Pause the take at its next frame boundary (it stays one take)");
  CLI::App* resume = app.add_subcommand("resume", "Resume the paused take (the pause is a gap in its ledger)");
  CLI::App* abort_cmd =
      app.add_subcommand("abort", "Abort the armed, capturing or paused take; what it recorded is kept");
  for (CLI::App* cmd : {pause, resume, abort_cmd}) cmd->add_flag("--json", session_json, "Print JSON for scripts");
  std::string estop_reason;
  bool estop_reset = false, estop_json = false;
  CLI::App* estop = app.add_subcommand(
      "estop",
      "Emergency stop: every light node blacks out now (all at once), a take in progress is aborted, and nothing arms "
      "until `stagectl estop --reset`. Exit 3 if a node did not confirm dark");
  estop->add_option("--reason", estop_reason, "Why, for the log and the stage's status");
  estop->add_flag("--reset", estop_reset, "Release the latch: every light node leaves blackout (idle, dark)");
  estop->add_flag("--json", estop_json, "Print JSON for scripts");
  std::string preview_camera, preview_out;
  bool preview_json = false;
  CLI::App* preview =
      app.add_subcommand("preview", "Save a camera's latest preview from the take (a small PNG) to a file");
  preview->add_option("camera", preview_camera, "Camera id")->required();
  preview->add_option("-o,--output", preview_out, "PNG file to write (default CAMERA-preview.png)");
  preview->add_flag("--json", preview_json, "Print the preview's metadata as JSON");
  bool takes_json = false;
  CLI::App* takes = app.add_subcommand("takes", "List the takes in the catalog: state, outcome, frames, size");
  takes->add_flag("--json", takes_json, "Print JSON for scripts");
  CLI::App* take = app.add_subcommand("take", "One take");
  take->require_subcommand(1);
  std::string take_id;
  bool take_json = false;
  CLI::App* take_show = take->add_subcommand("show", "A take's ledger summary, per role and camera, and its self-test");
  take_show->add_option("id", take_id, "Take id (stagectl takes lists them), or latest")->required();
  take_show->add_flag("--json", take_json, "Print JSON for scripts");
  std::string ledger_id, ledger_camera;
  bool ledger_lost = false, ledger_json = false;
  CLI::App* take_ledger = take->add_subcommand(
      "ledger", "A take's ledger: every expected (camera, slot) and what became of it (stored, or lost and why)");
  take_ledger->add_option("id", ledger_id, "Take id, or latest")->required();
  take_ledger->add_option("--camera", ledger_camera, "Only this camera's entries");
  take_ledger->add_flag("--lost", ledger_lost, "Only the entries that were lost (neither stored nor paused)");
  take_ledger->add_flag("--json", ledger_json, "Print one LedgerEntry as JSON per line");
  std::string watch_id;
  bool watch_json = false;
  CLI::App* watch = app.add_subcommand(
      "watch",
      "Follow the running take (or TAKE) to its end, as `capture` shows it: for a console that reconnects, or a take "
      "another client started. Exit codes as for capture; a take that has ended gives its verdict at once");
  watch->add_option("take", watch_id, "Take id (default: the one the session holds)");
  watch->add_flag("--json", watch_json, "Print the take's summary as JSON (progress still goes to stderr)");

  ProcessFlags pf;
  CLI::App* process =
      app.add_subcommand("process",
                         "Run a processing stage over a take on one of the stage's processing workers (results in "
                         "TAKE/derived/STAGE/), with progress");
  process->add_option("id", pf.take_id, "Take id (stagectl takes lists them), or latest")->required();
  process
      ->add_option("--stage", pf.stage,
                   "The stage: graph (every stage the outputs asked for need, what is up to date skipped: "
                   "--stages, --with; docs/processing.md#the-graph), photometric, calibration, mvs, fit (the face "
                   "template on multi-view stereo's "
                   "meshes, or on --geometry's), textures (the photometric maps fused into the fit's UV layout), "
                   "stabilize (the textures warped onto the first frame's), or the neural asset's: asset-dataset "
                   "(TAKE/derived/asset/dataset.h5), asset-train (a network on it, --network) and asset-infer (the "
                   "asset driven from --cameras' one camera; docs/asset.md)")
      ->capture_default_str();
  process->add_option("--frames", pf.frames, "Virtual frames A:B (B excluded), A: to the end, or A")
      ->capture_default_str();
  process->add_option("--stages", pf.graph_stages,
                      "--stage graph: the outputs asked for, comma-separated (calibration, mvs, photometric, fit, "
                      "textures, stabilize; default: all but calibration)");
  process->add_option("--chunk-frames", pf.chunk_frames, "--stage graph: frames per task (default 4)");
  process->add_option("--with", pf.with,
                      "--stage graph: a stage's own flag as stage-process takes it, STAGE:FLAG (e.g. "
                      "textures:--size=512); repeat for more");
  process->add_option("--retries", pf.retries, "--stage graph: runs a failed task again this many times (default 1)")
      ->check(CLI::Range(0, 100));
  process->add_option("--jobs", pf.jobs, "--stage graph: tasks at a time on the worker (default 1)")
      ->check(CLI::Range(0, 256));
  process->add_option("--cameras", pf.cameras,
                      "Camera ids, comma-separated (default: the stage's; photometric: every high-speed camera, "
                      "calibration: every camera)");
  process->add_option("--geometry", pf.geometry,
                      "Photometric stereo's surface geometry, or the surfaces --stage fit fits: mvs (multi-view "
                      "stereo's meshes: process --stage mvs first; the default), none, or a directory of "
                      "frame-NNNNNN/mesh.obj relative to the take (ground_truth on the simulated stage: the truth's)");
  process->add_option("--calibration", pf.calibration,
                      "Where the cameras are: a calibration file or a directory holding cameras.json, relative to the "
                      "take or absolute (e.g. ground_truth on the simulated stage); default: the rig's nominal models");
  process->add_option("--texture-size", pf.texture_size, "--stage textures: texels across the textures (default 4096)")
      ->check(CLI::Range(16, 16384));
  process
      ->add_option("--method", pf.stabilize_method,
                   "--stage stabilize: flow (OpenCV's DIS, the default) or unet (the self-supervised U-Net, "
                   "trained on the frames)")
      ->check(CLI::IsMember({"flow", "unet"}));
  process->add_option("--source", pf.asset_source, "--stage asset-dataset: where the geometry comes from")
      ->check(CLI::IsMember({"truth", "reconstruction"}));
  process->add_option("--geometry-size", pf.geometry_size, "--stage asset-dataset: texels across the geometry maps")
      ->check(CLI::Range(16, 1024));
  process->add_option("--image-size", pf.image_size, "--stage asset-dataset: pixels across a crop")
      ->check(CLI::Range(16, 512));
  process->add_option("--frame-step", pf.frame_step, "--stage asset-dataset: every Nth frame (default 1)")
      ->check(CLI::Range(1, 1000));
  process->add_option("--crop-mm", pf.crop_mm, "--stage asset-dataset: the square cropped about the face, mm")
      ->check(CLI::Range(50.0, 1000.0));
  process
      ->add_option("--network", pf.network,
                   "--stage asset-train: geometry (the default), expression, mapping, finetune, texture or "
                   "texture-mapping")
      ->check(CLI::IsMember({"geometry", "expression", "mapping", "finetune", "texture", "texture-mapping"}));
  process->add_option("--iterations", pf.iterations, "--stage asset-train: Adam steps (default: the network's)")
      ->check(CLI::Range(1, 10000000));
  process->add_option("--batch", pf.batch, "--stage asset-train: samples a step (default: the network's)")
      ->check(CLI::Range(1, 1024));
  process->add_option("--learning-rate", pf.learning_rate, "--stage asset-train: Adam's rate (default: the network's)")
      ->check(CLI::Range(1e-7, 1.0));
  process->add_option("--input-size", pf.input_size, "--stage asset-train: texels (pixels) across the net's input")
      ->check(CLI::Range(16, 1024));
  process->add_option("--levels", pf.levels, "--stage asset-train: stride-2 levels of a VAE")->check(CLI::Range(1, 8));
  process->add_option("--held-out-cameras", pf.held_out_cameras,
                      "--stage asset-train --network expression: cameras it never sees, comma-separated");
  process
      ->add_option("--region-weight", pf.region_weight,
                   "--stage asset-train --network geometry: weight of the texels about the eyes and the mouth")
      ->check(CLI::Range(1.0, 1000.0));
  process
      ->add_option("--map-loss", pf.map_loss,
                   "--stage asset-train --network finetune: the loss on the decoded maps, the eyes' and the mouth's "
                   "texels weighing this many times")
      ->check(CLI::Range(1.0, 1000.0));
  process->add_option("--worker", pf.worker, "The worker's id (default: the first that is up)");
  process->add_flag("--json", pf.json, "Print the result as JSON");

  CalibrateFlags calf;
  CLI::App* calibrate = app.add_subcommand(
      "calibrate",
      "Record a calibration take (the ChArUco board moved through the stage's volume; on the simulated stage, "
      "stage-sim --set sim.subject.kind=charuco) and calibrate every camera from it on a processing worker: "
      "TAKE/derived/calibration/cameras.json, which later stages take with --calibration");
  calibrate->add_option("--seconds", calf.seconds, "Seconds to record")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  calibrate->add_option("--name", calf.name, "The take's name in the catalog")->capture_default_str();
  calibrate->add_option("--worker", calf.worker, "The worker's id (default: the first that is up)");
  calibrate->add_flag("--json", calf.json, "Print the calibration's result as JSON");
  calibrate
      ->add_option("--ground-truth", calf.ground_truth,
                   "Simulated stage: how much ground truth the take gets (full, scene or none); scene holds the "
                   "true cameras the calibration is judged against")
      ->check(CLI::IsMember(kGroundTruthScopes))
      ->capture_default_str();

  FaultFlags ff;
  CLI::App* sim = app.add_subcommand("sim", "The simulated stage (stage-sim): inject faults into its world");
  sim->require_subcommand(1);
  CLI::App* fault = sim->add_subcommand(
      "fault",
      "Inject a fault now: an LED unit goes dark (--dead) or late (--delay-us), a light node late (--delay-us), a "
      "camera misses triggers or drops frames, its clock jumps or drifts, a node crashes (--crash-at-s). A unit's "
      "fault replaces its state (--delay-us 0 without --dead revives it); a node's sets the fields given");
  fault->add_option("target", ff.target, "LED unit, light node or camera id")->required();
  fault->add_option("--world", ff.world, "SimWorld address host:port (default: from the endpoint file)");
  fault->add_flag("--dead", ff.dead, "LED unit: dark");
  fault->add_option("--delay-us", ff.delay_us, "LED unit or light node: light this late after the switch, us");
  fault->add_option("--miss-triggers", ff.miss_triggers, "Camera: fraction of triggers missed")
      ->check(CLI::Range(0.0, 1.0));
  fault->add_option("--drop-frames", ff.drop_frames, "Camera: fraction of exposed frames lost")
      ->check(CLI::Range(0.0, 1.0));
  fault->add_option("--clock-offset-us", ff.clock_offset_us, "Camera: clock offset against the world, us");
  fault->add_option("--clock-drift-ppm", ff.clock_drift_ppm, "Camera: clock drift, ppm");
  fault->add_option("--crash-at-s", ff.crash_at_s, "Light node or camera: dies once the world passes this time, s");
  fault->add_option("--drop-slots", ff.drop_slots, "Camera: loses the frames of these world slots");
  fault->add_option("--extra-steps", ff.extra_steps,
                    "Light node: its board steps this many extra times at its next edge (its table runs ahead)");

  if (auto code = stage::ParseCommandLine(app, argc, argv)) return *code;
  if (auto s = stage::InitLogging(kProgram, log_level); !s.ok()) return stage::ReportFatal(kProgram, s);
  const char* user = std::getenv("USER");
  if (auto s = stage::UseStageSecurity(&c, absl::StrCat("operator/", user != nullptr ? user : "root")); !s.ok()) {
    return stage::ReportFatal(kProgram, s);
  }

  if (status->parsed()) return Status(c, json, status_cameras);
  if (cameras->parsed()) return Cameras(json);
  if (check->parsed()) return TimingCheck(c, tf);
  if (show->parsed()) return TimingShow(c, tf);
  if (exporter->parsed()) return TimingExport(c, tf);
  if (rehearse->parsed()) return TimingRehearse(c, rehearse_slots, rehearse_json);
  if (fault->parsed()) return SimFault(c, ff);
  if (capture->parsed()) {
    // Without --frames or --seconds: the armed take as armed.
    return Capture(c, capture_frames, capture_seconds, capture_name, capture_json, false,
                   no_ground_truth ? stage::v1::GROUND_TRUTH_SCOPE_NONE : kGroundTruthScopes.at(capture_truth));
  }
  if (arm->parsed()) {
    if (arm_frames == 0 && arm_seconds == 0) {
      return stage::ReportFatal(kProgram, absl::InvalidArgumentError("arm: give --frames N or --seconds S"));
    }
    return Capture(c, arm_frames, arm_seconds, arm_name, arm_json, /*arm_only=*/true);
  }
  if (pause->parsed()) return Session(c, "pause", session_json);
  if (resume->parsed()) return Session(c, "resume", session_json);
  if (abort_cmd->parsed()) return Session(c, "abort", session_json);
  if (estop->parsed()) return EStop(c, estop_reason, estop_reset, estop_json);
  if (preview->parsed()) return Preview(c, preview_camera, preview_out, preview_json);
  if (takes->parsed()) return Takes(c, takes_json);
  if (take_show->parsed()) return TakeShow(c, take_id, take_json);
  if (take_ledger->parsed()) return Ledger(c, ledger_id, ledger_camera, ledger_lost, ledger_json);
  if (watch->parsed()) return Watch(c, watch_id, watch_json);
  if (process->parsed()) return Process(c, pf);
  if (calibrate->parsed()) return Calibrate(c, calf);
  return 2;
}
