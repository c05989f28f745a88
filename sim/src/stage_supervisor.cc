// stage-sim's supervisor: start, watch and stop the processes of a simulated stage.
#include "stage/sim/stage_supervisor.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "absl/strings/strip.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
#include "stage/common/proto_json.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"
#include "stage/common/status.h"
#include "stage/v1/controller.grpc.pb.h"

namespace stage::sim {
namespace {

namespace fs = std::filesystem;

// The file's text, or "" when it does not exist (yet): port files appear once a child serves.
std::string ReadFile(const std::string& path) { return ReadFileToString(path).value_or(""); }

// Protobuf's JSON mapping with the proto field names, as the programs that read these files expect.
absl::StatusOr<std::string> ToJson(const google::protobuf::Message& message) {
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  print.add_whitespace = true;
  if (auto s = google::protobuf::util::MessageToJsonString(message, &json, print); !s.ok()) {
    return absl::InternalError(absl::StrCat("cannot serialize ", message.GetTypeName(), ": ", s.message().as_string()));
  }
  return json;
}

bool ProcessAlive(pid_t pid) { return pid > 0 && (kill(pid, 0) == 0 || errno == EPERM); }

// The effective rig lives in the run directory: every path the rig file gave relative to itself (a pattern-set file,
// the certificates, the take root, a performance, a head asset's mesh, blendshapes and maps) is made absolute against
// the file's folder, so that it still points where it did.
void MakeRigPathsAbsolute(v1::RigConfig* rig, const std::string& base_dir) {
  auto absolute = [&](std::string* file) {
    if (file->empty()) return;
    const std::filesystem::path given(*file);
    if (given.is_relative()) *file = std::filesystem::absolute(std::filesystem::path(base_dir) / given).string();
  };
  if (!IsBuiltinPatternSet(rig->pattern_set())) absolute(rig->mutable_pattern_set());
  absolute(rig->mutable_security()->mutable_ca_file());
  absolute(rig->mutable_security()->mutable_cert_dir());
  absolute(rig->mutable_storage()->mutable_root());
  v1::SimSubject* subject = rig->mutable_sim()->mutable_subject();
  const std::string& performance = subject->performance();
  if (performance != "default" && performance != "still" && performance != "range_of_motion" && !performance.empty()) {
    absolute(subject->mutable_performance());
  }
  v1::SimHeadAsset* asset = subject->mutable_asset();
  for (std::string* file : {asset->mutable_neutral_obj(), asset->mutable_albedo(), asset->mutable_specular(),
                            asset->mutable_roughness(), asset->mutable_normal()}) {
    absolute(file);
  }
  for (auto& [expression, file] : *asset->mutable_blendshapes()) absolute(&file);
}

}  // namespace

std::string LastLineOf(const std::string& path) {
  std::string text = ReadFile(path);
  absl::string_view view = absl::StripTrailingAsciiWhitespace(text);
  size_t cut = view.rfind('\n');
  return std::string(cut == absl::string_view::npos ? view : view.substr(cut + 1));
}

absl::Status StageSupervisorOptions::Validate() const {
  if (run_dir.empty()) return absl::InvalidArgumentError("run_dir is empty");
  if (bin_dir.empty()) return absl::InvalidArgumentError("bin_dir is empty");
  for (const char* program : {"camera-node", "light-node", "processing-worker", "stage-controller"}) {
    std::string path = absl::StrCat(bin_dir, "/", program);
    if (access(path.c_str(), X_OK) != 0) {
      return absl::NotFoundError(absl::StrCat(path, " is missing or not executable (build first, or pass --bin-dir)"));
    }
  }
  std::string host;
  int port;
  STAGE_RETURN_IF_ERROR(Annotate(ParseHostPort(controller_listen, &host, &port), "--listen"));
  for (const auto& [who, place] : placements) {
    const std::string what = absl::StrCat("--place ", who);
    if (place.netns.empty() || place.netns.find('/') != std::string::npos) {
      return absl::InvalidArgumentError(absl::StrCat(what, ": the network namespace needs a name (ip netns list)"));
    }
    if (access(absl::StrCat("/run/netns/", place.netns).c_str(), F_OK) != 0) {
      return absl::NotFoundError(absl::StrCat(what, ": no network namespace ", place.netns, " (ip netns add it)"));
    }
    STAGE_RETURN_IF_ERROR(Annotate(ParseHostPort(absl::StrCat(place.host, ":0"), &host, &port), what));
  }
  if (startup_timeout.count() <= 0) return absl::InvalidArgumentError("startup timeout must be > 0");
  if (grace.count() < 0) return absl::InvalidArgumentError("grace period must be >= 0");
  return absl::OkStatus();
}

StageSupervisor::StageSupervisor(StageSupervisorOptions options) : options_(std::move(options)) {}

StageSupervisor::~StageSupervisor() { Stop(); }

absl::Status StageSupervisor::PrepareRunDir() {
  std::error_code ec;
  fs::create_directories(options_.run_dir + "/logs", ec);
  if (!ec) fs::create_directories(options_.run_dir + "/ports", ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat("cannot create ", options_.run_dir, ": ", ec.message()));
  // Another stage-sim on the same run directory would overwrite its endpoint file: refuse.
  if (fs::exists(endpoints_path())) {
    v1::SimEndpoints other;
    if (FromContractJson(ReadFile(endpoints_path()), &other).ok() && other.stage_sim_pid() != getpid() &&
        ProcessAlive(other.stage_sim_pid())) {
      return absl::FailedPreconditionError(absl::StrCat("another stage-sim (pid ", other.stage_sim_pid(),
                                                        ") is running with run directory ", options_.run_dir,
                                                        "; stop it or pass --run-dir"));
    }
    fs::remove(endpoints_path(), ec);
  }
  for (const auto& entry : fs::directory_iterator(options_.run_dir + "/ports", ec)) fs::remove(entry.path(), ec);
  return absl::OkStatus();
}

absl::Status StageSupervisor::SpawnChild(const std::string& program, const std::string& id, v1::NodeKind kind,
                                         const std::string& config, const std::string& listen,
                                         std::vector<std::string> extra_args) {
  Child child;
  child.id = id;
  child.kind = kind;
  child.program = program;
  child.port_file = absl::StrCat(options_.run_dir, "/ports/", id, ".addr");
  child.log_file = absl::StrCat(options_.run_dir, "/logs/", id, ".log");
  const StageSupervisorOptions::Placement* place = PlacementOf(id, kind);
  SubprocessOptions sp;
  if (place != nullptr) sp.argv = {"ip", "netns", "exec", place->netns};  // ip execs the node: the same pid
  const std::string local = place != nullptr ? place->host : "127.0.0.1";
  for (std::string a : {absl::StrCat(options_.bin_dir, "/", program), std::string("--config"), config,
                        std::string("--listen"), place != nullptr ? absl::StrCat(place->host, ":0") : listen,
                        std::string("--port-file"), child.port_file}) {
    sp.argv.push_back(std::move(a));
  }
  if (!options_.child_log_level.empty()) {
    sp.argv.push_back("--log-level");
    sp.argv.push_back(options_.child_log_level);
  }
  if (options_.metrics) {
    child.metrics_file = absl::StrCat(options_.run_dir, "/ports/", id, ".metrics");
    for (std::string a : {std::string("--metrics-listen"), absl::StrCat(local, ":0"), std::string("--metrics-port-file")}) {
      sp.argv.push_back(std::move(a));
    }
    sp.argv.push_back(child.metrics_file);
  }
  for (std::string& a : extra_args) sp.argv.push_back(std::move(a));
  // A simulated camera renders a moving subject's responses into new matrices of tens of MB for every pose, from its
  // device's threads: glibc gave them fresh pages (a thread arena's heap is unmapped once empty, whatever the trim
  // threshold), paying page faults and the kernel's zeroing each time. One arena with large blocks kept in it reuses
  // them: a 6-frame ChArUco take at render scale 0.125 took 145 s (54 s of system time) without, 123 s (42 s) with it
  // set for every process and 138 s (47 s) for the cameras only, on a 2-core machine (runs of one take; noisy).
  // The caller's own GLIBC_TUNABLES wins.
  if (kind == v1::NODE_KIND_CAMERA && std::getenv("GLIBC_TUNABLES") == nullptr) {
    sp.env.push_back(
        "GLIBC_TUNABLES=glibc.malloc.arena_max=1:glibc.malloc.mmap_threshold=1073741824:"
        "glibc.malloc.trim_threshold=4294967296");
  }
  sp.stdout_path = child.log_file;
  sp.stderr_path = child.log_file;
  auto process = Subprocess::Spawn(sp);
  if (!process.ok()) return Annotate(process.status(), absl::StrCat("starting ", program, " ", id));
  child.process = std::move(*process);
  Logger("sim.stage")->debug("started {} {} (pid {})", program, id, child.process->pid());
  children_.push_back(std::move(child));
  return absl::OkStatus();
}

const StageSupervisorOptions::Placement* StageSupervisor::PlacementOf(const std::string& id, v1::NodeKind kind) const {
  if (auto it = options_.placements.find(id); it != options_.placements.end()) return &it->second;
  const char* name = kind == v1::NODE_KIND_CAMERA                ? "camera"
                     : kind == v1::NODE_KIND_LIGHT               ? "light"
                     : kind == v1::NODE_KIND_PROCESSING_WORKER   ? "worker"
                     : kind == v1::NODE_KIND_CONTROLLER          ? "controller"
                                                                 : "";
  if (auto it = options_.placements.find(name); it != options_.placements.end()) return &it->second;
  return nullptr;
}

std::string StageSupervisor::DescribeExit(const Child& child) const {
  std::string last = LastLineOf(child.log_file);
  return absl::StrCat(child.program, " ", child.id, " (pid ", child.process->pid(),
                      ") exited: ", child.process->exit_info()->Describe(), "; log ", child.log_file,
                      last.empty() ? "" : absl::StrCat(" ends: ", last));
}

absl::Status StageSupervisor::WaitForAddresses(std::chrono::steady_clock::time_point deadline) {
  while (true) {
    size_t pending = 0;
    for (Child& child : children_) {
      if (!child.address.empty()) continue;
      if (child.process->Poll()) {
        child.reported = true;
        return absl::UnavailableError(absl::StrCat("before serving, ", DescribeExit(child)));
      }
      std::string text = ReadFile(child.port_file);
      absl::string_view address = absl::StripAsciiWhitespace(text);
      if (address.empty()) {
        ++pending;
        continue;
      }
      child.address = std::string(address);
      if (!child.metrics_file.empty()) {
        // Written before the address file (StartMetrics, then the gRPC address): there once the address is.
        std::string metrics = ReadFile(child.metrics_file);
        child.metrics = std::string(absl::StripAsciiWhitespace(metrics));
        if (child.metrics.empty()) {
          return absl::InternalError(absl::StrCat(child.program, " ", child.id,
                                                  " serves gRPC but wrote no metrics "
                                                  "address to ",
                                                  child.metrics_file, "; log ", child.log_file));
        }
      }
    }
    if (pending == 0) return absl::OkStatus();
    if (std::chrono::steady_clock::now() > deadline) {
      for (const Child& child : children_) {
        if (child.address.empty()) {
          return absl::DeadlineExceededError(absl::StrCat(child.program, " ", child.id, " (pid ", child.process->pid(),
                                                          ") did not start serving in time; log ", child.log_file));
        }
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

absl::Status StageSupervisor::WriteEffectiveRig(const std::string& path, bool with_addresses) {
  v1::RigConfig rig = rig_.rig;
  auto address_of = [&](const std::string& id) {
    for (const Child& c : children_) {
      if (c.id == id) return c.address;
    }
    return std::string();
  };
  if (with_addresses) {
    for (auto& c : *rig.mutable_cameras()) c.set_address(address_of(c.id()));
    for (auto& n : *rig.mutable_light_nodes()) n.set_address(address_of(n.id()));
    for (auto& w : *rig.mutable_processing_workers()) w.set_address(address_of(w.id()));
  }
  MakeRigPathsAbsolute(&rig, rig_.base_dir);
  // The controller listens where stage-sim says (--listen), whatever the rig's controller.listen is.
  STAGE_ASSIGN_OR_RETURN(std::string json, ToJson(rig));
  return WriteFileAtomically(path, json);
}

absl::Status StageSupervisor::WaitForStageUp(std::chrono::steady_clock::time_point deadline) {
  const Child& controller = children_.back();
  auto channel = MakeChannel(controller.address);
  auto stub = v1::StageController::NewStub(channel);
  auto log = Logger("sim.stage");
  int last_up = -1;
  std::string not_up;
  while (true) {
    for (Child& child : children_) {
      if (child.process->Poll()) {
        child.reported = true;
        return absl::UnavailableError(absl::StrCat("while the stage came up, ", DescribeExit(child)));
      }
    }
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
    v1::StageStatus status;
    grpc::Status rpc = stub->GetStageStatus(&context, v1::GetStageStatusRequest(), &status);
    if (rpc.ok()) {
      if (status.nodes_up() != last_up) {
        last_up = status.nodes_up();
        log->info("{} of {} nodes up", status.nodes_up(), status.nodes_total());
      }
      if (status.nodes_up() == status.nodes_total()) return absl::OkStatus();
      not_up.clear();
      for (const auto& n : status.nodes()) {
        if (n.state() != v1::NODE_STATE_UP) {
          absl::StrAppend(&not_up, not_up.empty() ? "" : ", ", n.id(), " (", NodeStateName(n.state()), ": ", n.reason(),
                          ")");
        }
      }
    }
    if (std::chrono::steady_clock::now() > deadline) {
      return absl::DeadlineExceededError(
          absl::StrCat("the stage did not come up in time; ",
                       rpc.ok() ? absl::StrCat("not up: ", not_up)
                                : absl::StrCat("controller does not answer: ", rpc.error_message())));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
}

absl::Status StageSupervisor::WriteEndpoints() {
  endpoints_.Clear();
  endpoints_.set_controller(children_.back().address);
  endpoints_.set_stage_sim_pid(getpid());
  endpoints_.set_rig_file(options_.run_dir + "/rig.json");
  endpoints_.set_log_dir(options_.run_dir + "/logs");
  endpoints_.set_world(options_.world_address);
  endpoints_.set_metrics(options_.own_metrics);
  for (const Child& c : children_) {
    auto* p = endpoints_.add_processes();
    p->set_id(c.id);
    p->set_kind(c.kind);
    p->set_address(c.address);
    p->set_pid(c.process->pid());
    p->set_log_file(c.log_file);
    p->set_metrics(c.metrics);
  }
  STAGE_ASSIGN_OR_RETURN(std::string json, ToJson(endpoints_));
  return WriteFileAtomically(endpoints_path(), json);
}

absl::Status StageSupervisor::Start() {
  STAGE_RETURN_IF_ERROR(options_.Validate());
  STAGE_ASSIGN_OR_RETURN(rig_, LoadRig(options_.rig));
  if (!options_.overrides.empty()) {
    STAGE_ASSIGN_OR_RETURN(rig_, ApplyRigOverrides(rig_, options_.overrides));
  }
  if (rig_.rig.sim().gige_fakes() && options_.world_address.empty()) {
    return absl::InvalidArgumentError("sim.gige_fakes: the fake cameras render the world; --world none has none");
  }
  if (rig_.rig.sim().modbus_fakes() && options_.world_address.empty()) {
    return absl::InvalidArgumentError("sim.modbus_fakes: the fake LED boards light the world; --world none has none");
  }
  STAGE_RETURN_IF_ERROR(PrepareRunDir());
  Logger("sim.stage")
      ->info("bringing up stage {} from {} (run directory {})", rig_.rig.stage().id(), rig_.source_name,
             options_.run_dir);
  started_ = true;
  auto deadline = std::chrono::steady_clock::now() + options_.startup_timeout;
  auto fail = [&](absl::Status s) {
    Stop();
    return s;
  };
  std::string config = options_.rig;
  if (config != kBuiltinRigName) config = fs::absolute(config).string();
  if (!options_.overrides.empty()) {
    // The nodes read the rig with the overrides applied.
    config = options_.run_dir + "/rig-set.json";
    if (auto s = WriteEffectiveRig(config, /*with_addresses=*/false); !s.ok()) return fail(s);
  }
  // Every device is simulated: the rig's hardware backends are overridden.
  auto device_args = [&](const std::string& id) {
    std::vector<std::string> args = {"--id", id, "--backend", "sim"};
    for (const auto& c : rig_.rig.cameras()) {
      // A fake GigE Vision camera of stage-sim's stands in for it: the node runs its real backend.
      if (c.id() == id && rig_.rig.sim().gige_fakes() && c.backend() == v1::CAMERA_BACKEND_ARAVIS)
        return std::vector<std::string>{"--id", id};
    }
    for (const auto& n : rig_.rig.light_nodes()) {
      // A fake LED board of stage-sim's stands in for it (modbus.tcp points there): the node runs its real backend.
      if (n.id() == id && rig_.rig.sim().modbus_fakes() && n.backend() == v1::LIGHT_BACKEND_MODBUS) {
        return std::vector<std::string>{"--id", id};
      }
    }
    if (!options_.world_address.empty()) {
      args.push_back("--sim-world");
      args.push_back(options_.world_address);
    }
    return args;
  };
  for (const auto& c : rig_.rig.cameras()) {
    if (auto s = SpawnChild("camera-node", c.id(), v1::NODE_KIND_CAMERA, config, "127.0.0.1:0", device_args(c.id()));
        !s.ok()) {
      return fail(s);
    }
  }
  for (const auto& n : rig_.rig.light_nodes()) {
    std::vector<std::string> args = device_args(n.id());
    const bool in_world = std::find(args.begin(), args.end(), "--sim-world") != args.end();
    if (in_world && options_.self_armed_world) args.push_back("--sim-self-arm");
    if (auto s = SpawnChild("light-node", n.id(), v1::NODE_KIND_LIGHT, config, "127.0.0.1:0", std::move(args));
        !s.ok()) {
      return fail(s);
    }
  }
  for (const auto& w : rig_.rig.processing_workers()) {
    if (auto s = SpawnChild("processing-worker", w.id(), v1::NODE_KIND_PROCESSING_WORKER, config, "127.0.0.1:0",
                            {"--id", w.id()});
        !s.ok()) {
      return fail(s);
    }
  }
  if (auto s = WaitForAddresses(deadline); !s.ok()) return fail(s);
  std::string effective = options_.run_dir + "/rig.json";
  if (auto s = WriteEffectiveRig(effective); !s.ok()) return fail(s);
  std::vector<std::string> controller_args;
  if (!options_.world_address.empty() && !options_.self_armed_world) {
    controller_args = {"--sim-world", options_.world_address};
  }
  {
    std::error_code ec;
    const std::string root = options_.take_root.empty() ? rig_.rig.storage().root() : options_.take_root;
    controller_args.push_back("--take-root");
    controller_args.push_back(fs::absolute(root, ec).lexically_normal().string());
  }
  if (auto s = SpawnChild("stage-controller", "controller", v1::NODE_KIND_CONTROLLER, effective,
                          options_.controller_listen, controller_args);
      !s.ok()) {
    return fail(s);
  }
  if (auto s = WaitForAddresses(deadline); !s.ok()) return fail(s);
  if (auto s = WaitForStageUp(deadline); !s.ok()) return fail(s);
  if (auto s = WriteEndpoints(); !s.ok()) return fail(s);
  return absl::OkStatus();
}

std::vector<std::string> StageSupervisor::ReapExited() {
  std::vector<std::string> lines;
  for (Child& child : children_) {
    if (!child.reported && child.process->Poll()) {
      child.reported = true;
      lines.push_back(DescribeExit(child));
    }
  }
  return lines;
}

int StageSupervisor::Stop() {
  if (!started_) return 0;
  started_ = false;
  // Signal everyone first, then wait: stopping 35 processes one after another would take 35 grace periods.
  for (Child& child : children_) child.process->Signal(SIGTERM);
  auto deadline = std::chrono::steady_clock::now() + options_.grace;
  int killed = 0;
  for (Child& child : children_) {
    auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (child.process->Wait(std::max(left, std::chrono::milliseconds(0)))) continue;
    Logger("sim.stage")
        ->warn("{} {} (pid {}) did not stop within {} ms of SIGTERM; sending SIGKILL", child.program, child.id,
               child.process->pid(), options_.grace.count());
    child.process->Signal(SIGKILL);
    child.process->Wait();
    ++killed;
  }
  std::error_code ec;
  fs::remove(endpoints_path(), ec);
  return killed;
}

}  // namespace stage::sim
