// The processing graph's units, keys and manifests, its plan file, and one task's run (graph.h, graph_internal.h).
#include <fcntl.h>
#include <openssl/evp.h>
#include <stdio.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "graph_internal.h"
#include "stage/common/file_util.h"
#include "stage/common/node_info.h"
#include "stage/common/status.h"
#include "stage/common/version.h"

namespace stage::processing {
namespace fs = std::filesystem;
using nlohmann::ordered_json;

namespace internal {

namespace {

std::string Hex(const unsigned char* bytes, unsigned int n) {
  std::string out;
  out.reserve(2 * n);
  for (unsigned int i = 0; i < n; ++i) absl::StrAppendFormat(&out, "%02x", bytes[i]);
  return out;
}

// Streams bytes into a SHA-256.
class Sha256 {
 public:
  Sha256() : ctx_(EVP_MD_CTX_new()) { EVP_DigestInit_ex(ctx_, EVP_sha256(), nullptr); }
  ~Sha256() { EVP_MD_CTX_free(ctx_); }
  Sha256(const Sha256&) = delete;
  Sha256& operator=(const Sha256&) = delete;
  void Add(const void* data, size_t n) { EVP_DigestUpdate(ctx_, data, n); }
  std::string Hex() {
    unsigned char out[EVP_MAX_MD_SIZE];
    unsigned int n = 0;
    EVP_DigestFinal_ex(ctx_, out, &n);
    return internal::Hex(out, n);
  }

 private:
  EVP_MD_CTX* ctx_;
};

std::string OutputDir(const GraphPlan& plan, GraphStage stage) {
  return absl::StrCat(plan.take_dir, "/derived/", SpecOf(stage).output);
}

absl::StatusOr<ordered_json> ReadManifest(const std::string& dir) {
  const std::string path = dir + "/manifest.json";
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, "manifest"));
  ordered_json j = ordered_json::parse(text, nullptr, false);
  bool ok = !j.is_discarded() && j.is_object() && j.contains("key") && j["key"].is_string() &&
            j.contains("output_sha256") && j["output_sha256"].is_string() && j.contains("made_from") &&
            j["made_from"].is_object() && j.contains("outputs") && j["outputs"].is_array();
  for (size_t i = 0; ok && i < j["outputs"].size(); ++i) {
    const ordered_json& f = j["outputs"][i];
    ok = f.is_object() && f.contains("path") && f["path"].is_string() && f.contains("bytes") &&
         f["bytes"].is_number_unsigned();
  }
  if (!ok) return absl::DataLossError(absl::StrCat(path, ": not a processing manifest"));
  return j;
}

// Every regular file under `dir` but the manifest, by path relative to it, sorted.
std::vector<std::string> FilesUnder(const std::string& dir) {
  std::vector<std::string> out;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    if (!it->is_regular_file()) continue;
    std::string rel = fs::relative(it->path(), dir).string();
    if (rel != "manifest.json") out.push_back(std::move(rel));
  }
  std::sort(out.begin(), out.end());
  return out;
}

// The units of `stage` (a stage the task reads) that the task's unit `unit` is made from.
std::vector<Unit> InputUnits(const GraphPlan& plan, const GraphTask& task, const Unit& unit, const StageInput& in) {
  const Grain grain = SpecOf(in.stage).grain;
  if (grain == Grain::kTake) return {Unit{}};
  if (in.need == Need::kSameFrame && SpecOf(task.stage).grain == Grain::kFrame) {
    return {Unit{absl::StrFormat("frame-%06d", unit.frame), unit.frame}};
  }
  std::vector<Unit> out;
  for (int64_t f = plan.first_frame; f < plan.last_frame; ++f) out.push_back({absl::StrFormat("frame-%06d", f), f});
  return out;
}

}  // namespace

std::string Sha256Hex(const std::string& bytes) {
  Sha256 h;
  h.Add(bytes.data(), bytes.size());
  return h.Hex();
}

absl::StatusOr<std::string> FileSha256(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot read"));
  Sha256 h;
  std::vector<char> buffer(1 << 20);
  while (in) {
    in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    h.Add(buffer.data(), static_cast<size_t>(in.gcount()));
  }
  if (in.bad()) return absl::DataLossError(absl::StrCat(path, ": read failed"));
  return h.Hex();
}

absl::StatusOr<std::string> RecordingSha256(const std::string& take_dir) {
  STAGE_ASSIGN_OR_RETURN(const std::string take_json, ReadFileToString(take_dir + "/take.json", "take description"));
  std::string text = take_json;
  std::vector<std::pair<std::string, uintmax_t>> files;
  std::error_code ec;
  for (fs::directory_iterator it(take_dir + "/cameras", ec), end; !ec && it != end; it.increment(ec)) {
    if (it->is_regular_file()) files.emplace_back(it->path().filename().string(), it->file_size());
  }
  std::sort(files.begin(), files.end());
  for (const auto& [name, size] : files) absl::StrAppend(&text, "\n", name, " ", size);
  return Sha256Hex(text);
}

absl::StatusOr<int64_t> TakeFrames(const std::string& take_dir) {
  const std::string path = take_dir + "/take.json";
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, "take description"));
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  const nlohmann::json* frames = nullptr;
  if (!j.is_discarded() && j.contains("summary") && j["summary"].contains("frames")) frames = &j["summary"]["frames"];
  int64_t n = -1;
  if (frames != nullptr && frames->is_string()) {
    n = std::strtoll(frames->get<std::string>().c_str(), nullptr, 10);
  } else if (frames != nullptr && frames->is_number_integer()) {
    n = frames->get<int64_t>();
  }
  if (n <= 0) {
    return absl::FailedPreconditionError(
        absl::StrCat(path, ": no frames in its summary (a take still recording, or not a FaStage take)"));
  }
  return n;
}

std::vector<Unit> UnitsOf(const GraphPlan& plan, const GraphTask& task) {
  if (SpecOf(task.stage).grain == Grain::kTake) return {Unit{}};
  std::vector<Unit> out;
  for (int64_t f = task.first; f < task.last; ++f) out.push_back({absl::StrFormat("frame-%06d", f), f});
  return out;
}

std::string UnitDir(const GraphPlan& plan, GraphStage stage, const Unit& unit) {
  return unit.rel.empty() ? OutputDir(plan, stage) : absl::StrCat(OutputDir(plan, stage), "/", unit.rel);
}

absl::StatusOr<UnitKey> MakeUnitKey(const GraphPlan& plan, const GraphTask& task, const Unit& unit) {
  const StageSpec& spec = SpecOf(task.stage);
  ordered_json parts;
  parts["stage"] = spec.name;
  parts["software"] = std::string(kVersion);
  const auto args = plan.options.stage_args.find(task.stage);
  parts["flags"] = args == plan.options.stage_args.end() ? std::vector<std::string>{} : args->second;
  // A tracked or per-take stage's unit depends on where its run starts and ends; a frame's own does not.
  if (spec.grain != Grain::kFrame) parts["frames"] = {task.first, task.last};
  if (spec.reads_recording) parts["recording"] = plan.recording_sha256;
  if (spec.takes_calibration) {
    parts["calibration"] = {{"path", plan.options.calibration}, {"sha256", plan.calibration_sha256}};
  }
  parts["inputs"] = ordered_json::object();
  for (const StageInput& in : spec.inputs) {
    if (std::find(plan.stages.begin(), plan.stages.end(), in.stage) == plan.stages.end()) continue;
    std::string list;
    for (const Unit& u : InputUnits(plan, task, unit, in)) {
      const std::string dir = UnitDir(plan, in.stage, u);
      auto manifest = ReadManifest(dir);
      if (!manifest.ok()) {
        return absl::NotFoundError(absl::StrCat(fs::relative(dir, plan.take_dir).string(), " has no manifest"));
      }
      absl::StrAppend(&list, u.rel, " ", (*manifest)["output_sha256"].get<std::string>(), "\n");
    }
    parts["inputs"][std::string(GraphStageName(in.stage))] = Sha256Hex(list);
  }
  UnitKey key;
  key.parts = parts.dump();
  key.key = Sha256Hex(key.parts);
  return key;
}

absl::StatusOr<std::vector<UnitKey>> TaskUnitKeys(const GraphPlan& plan, const GraphTask& task,
                                                  const std::vector<Unit>& units) {
  std::vector<UnitKey> keys;
  for (const Unit& unit : units) {
    if (!keys.empty() && SpecOf(task.stage).grain != Grain::kFrame) {
      keys.push_back(keys.back());
      continue;
    }
    STAGE_ASSIGN_OR_RETURN(UnitKey key, MakeUnitKey(plan, task, unit));
    keys.push_back(std::move(key));
  }
  return keys;
}

std::string CompareManifest(const GraphPlan& plan, const GraphTask& task, const Unit& unit, const UnitKey& key) {
  const std::string dir = UnitDir(plan, task.stage, unit);
  auto manifest = ReadManifest(dir);
  if (absl::IsDataLoss(manifest.status())) return "stale: its manifest is unreadable";
  if (!manifest.ok()) return "missing";
  if ((*manifest)["key"] != key.key) {
    const ordered_json now = ordered_json::parse(key.parts);
    const ordered_json& then = (*manifest)["made_from"];
    for (const auto& [name, value] : now.items()) {
      if (!then.contains(name) || then.at(name) != value) {
        if (name == "inputs" && then.contains(name) && then.at(name).is_object()) {
          for (const auto& [stage, hash] : value.items()) {
            if (!then.at(name).contains(stage) || then.at(name).at(stage) != hash)
              return "stale: " + stage + " changed";
          }
        }
        return "stale: " + name + " changed";
      }
    }
    return "stale";
  }
  for (const auto& f : (*manifest)["outputs"]) {
    std::error_code ec;
    const std::string path = dir + "/" + f["path"].get<std::string>();
    if (fs::file_size(path, ec) != f["bytes"].get<uintmax_t>() || ec) return "outputs changed: " + path;
  }
  return "";
}

absl::Status WriteManifest(const std::string& dir, const GraphTask& task, const Unit& unit, const UnitKey& key) {
  ordered_json j;
  j["stage"] = GraphStageName(task.stage);
  if (unit.frame >= 0) j["frame"] = unit.frame;
  j["key"] = key.key;
  j["made_from"] = ordered_json::parse(key.parts);
  j["outputs"] = ordered_json::array();
  std::string list;
  for (const std::string& rel : FilesUnder(dir)) {
    STAGE_ASSIGN_OR_RETURN(const std::string sha, FileSha256(dir + "/" + rel));
    std::error_code ec;
    const uintmax_t bytes = fs::file_size(dir + "/" + rel, ec);
    j["outputs"].push_back({{"path", rel}, {"bytes", bytes}, {"sha256", sha}});
    absl::StrAppend(&list, rel, " ", sha, "\n");
  }
  j["output_sha256"] = Sha256Hex(list);
  return WriteFileAtomically(dir + "/manifest.json", j.dump(2) + "\n");
}

}  // namespace internal

namespace {

ordered_json PlanJson(const GraphPlan& plan) {
  ordered_json j;
  j["run_id"] = plan.run_id;
  j["take_dir"] = plan.take_dir;
  j["frames"] = {plan.first_frame, plan.last_frame};
  j["chunk_frames"] = plan.options.chunk_frames;
  j["calibration"] = plan.options.calibration;
  j["retries"] = plan.options.retries;
  j["recording_sha256"] = plan.recording_sha256;
  j["calibration_sha256"] = plan.calibration_sha256;
  j["asked"] = ordered_json::array();
  for (GraphStage s : plan.options.stages) j["asked"].push_back(GraphStageName(s));
  j["stages"] = ordered_json::array();
  for (GraphStage s : plan.stages) j["stages"].push_back(GraphStageName(s));
  j["stage_flags"] = ordered_json::object();
  for (const auto& [s, args] : plan.options.stage_args) j["stage_flags"][std::string(GraphStageName(s))] = args;
  j["tasks"] = ordered_json::array();
  for (const GraphTask& t : plan.tasks) {
    j["tasks"].push_back({{"stage", GraphStageName(t.stage)},
                          {"chunk", t.chunk},
                          {"frames", {t.first, t.last}},
                          {"needed", t.needed},
                          {"reason", t.reason}});
  }
  return j;
}

absl::StatusOr<GraphStage> StageFromJson(const nlohmann::json& name, const std::string& path) {
  auto s = name.is_string() ? ParseGraphStage(name.get<std::string>()) : std::nullopt;
  if (!s) return absl::DataLossError(absl::StrCat(path, ": unknown stage ", name.dump()));
  return *s;
}

}  // namespace

absl::Status WritePlan(const GraphPlan& plan) {
  std::error_code ec;
  fs::create_directories(plan.run_dir + "/logs", ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(plan.run_dir, "/logs: cannot create: ", ec.message()));
  // A run's status files and work directories are its own: the last run's would read as this one's.
  fs::remove_all(plan.run_dir + "/status", ec);
  fs::remove_all(plan.run_dir + "/work", ec);
  for (const GraphTask& t : plan.tasks) {
    if (t.needed) fs::remove(LogPath(plan, t), ec);
  }
  fs::create_directories(plan.run_dir + "/status", ec);
  return WriteFileAtomically(plan.run_dir + "/plan.json", PlanJson(plan).dump(2) + "\n");
}

absl::StatusOr<GraphPlan> ReadPlan(const std::string& run_dir) {
  const std::string path = run_dir + "/plan.json";
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, "processing plan"));
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.is_object()) return absl::DataLossError(absl::StrCat(path, ": not a processing plan"));
  try {
    GraphPlan plan;
    plan.run_id = j.at("run_id").get<std::string>();
    plan.take_dir = j.at("take_dir").get<std::string>();
    plan.run_dir = run_dir;
    plan.first_frame = j.at("frames").at(0).get<int64_t>();
    plan.last_frame = j.at("frames").at(1).get<int64_t>();
    plan.recording_sha256 = j.at("recording_sha256").get<std::string>();
    plan.calibration_sha256 = j.at("calibration_sha256").get<std::string>();
    GraphOptions& o = plan.options;
    o.take_dir = plan.take_dir;
    o.first_frame = plan.first_frame;
    o.last_frame = plan.last_frame;
    o.chunk_frames = j.at("chunk_frames").get<int64_t>();
    o.calibration = j.at("calibration").get<std::string>();
    o.retries = j.at("retries").get<int>();
    for (const auto& s : j.at("asked")) {
      STAGE_ASSIGN_OR_RETURN(o.stages.emplace_back(), StageFromJson(s, path));
    }
    for (const auto& s : j.at("stages")) {
      STAGE_ASSIGN_OR_RETURN(plan.stages.emplace_back(), StageFromJson(s, path));
    }
    for (const auto& [name, args] : j.at("stage_flags").items()) {
      STAGE_ASSIGN_OR_RETURN(const GraphStage s, StageFromJson(name, path));
      o.stage_args[s] = args.get<std::vector<std::string>>();
    }
    for (const auto& t : j.at("tasks")) {
      GraphTask task;
      STAGE_ASSIGN_OR_RETURN(task.stage, StageFromJson(t.at("stage"), path));
      task.chunk = t.at("chunk").get<int>();
      task.first = t.at("frames").at(0).get<int64_t>();
      task.last = t.at("frames").at(1).get<int64_t>();
      task.needed = t.at("needed").get<bool>();
      task.reason = t.at("reason").get<std::string>();
      plan.tasks.push_back(std::move(task));
    }
    return plan;
  } catch (const nlohmann::json::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
}

namespace {

// This process's CPU time so far, every thread, seconds.
double ProcessCpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// Puts `from` (a unit made in the work directory) where `to` is, replacing what was there.
absl::Status PutInPlace(const std::string& from, const std::string& to) {
  std::error_code ec;
  fs::create_directories(fs::path(to).parent_path(), ec);
  if (!fs::exists(to)) {
    fs::rename(from, to, ec);
    if (ec) return absl::InternalError(absl::StrCat("cannot move ", from, " to ", to, ": ", ec.message()));
    return absl::OkStatus();
  }
  // One step: the new unit and the old swap places (Linux 3.15+); the old, now at `from`, is then removed.
  if (renameat2(AT_FDCWD, from.c_str(), AT_FDCWD, to.c_str(), RENAME_EXCHANGE) != 0) {
    return absl::InternalError(absl::StrCat("cannot put ", from, " in place of ", to, ": ", std::strerror(errno)));
  }
  fs::remove_all(from, ec);
  return absl::OkStatus();
}

// The task's stale units made in `work` given their manifests and put in place; the stage's own files beside its
// frame directories (run.json) come from its first task only, so that every way of running the graph writes them
// alike.
absl::Status InstallUnits(const GraphPlan& plan, const GraphTask& task, const std::string& work,
                          const std::vector<std::pair<internal::Unit, internal::UnitKey>>& stale) {
  for (const auto& [unit, key] : stale) {
    const std::string made = unit.rel.empty() ? work : work + "/" + unit.rel;
    if (!fs::is_directory(made)) {
      return absl::InternalError(
          absl::StrCat(GraphStageName(task.stage), " made no ", unit.rel.empty() ? "output" : unit.rel, " in ", work));
    }
    STAGE_RETURN_IF_ERROR(internal::WriteManifest(made, task, unit, key));
    STAGE_RETURN_IF_ERROR(PutInPlace(made, internal::UnitDir(plan, task.stage, unit)));
  }
  if (SpecOf(task.stage).grain == Grain::kTake || task.chunk != 0) return absl::OkStatus();
  std::error_code ec;
  for (fs::directory_iterator it(work, ec), end; !ec && it != end; it.increment(ec)) {
    if (!it->is_regular_file()) continue;
    fs::rename(it->path(), internal::UnitDir(plan, task.stage, {}) + "/" + it->path().filename().string(), ec);
    if (ec) return absl::InternalError(absl::StrCat("cannot move ", it->path().string(), ": ", ec.message()));
  }
  return absl::OkStatus();
}

absl::Status RunStale(const GraphPlan& plan, const GraphTask& task, int attempt, const StageRunner& run,
                      const std::vector<std::pair<internal::Unit, internal::UnitKey>>& stale) {
  const StageSpec& spec = SpecOf(task.stage);
  const std::string work = absl::StrCat(plan.run_dir, "/work/", plan.TaskName(task), "-a", attempt);
  std::error_code ec;
  fs::remove_all(work, ec);
  fs::create_directories(work, ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(work, ": cannot create: ", ec.message()));
  std::vector<std::string> argv = {std::string(spec.name),
                                   "--take",
                                   plan.take_dir,
                                   "--frames",
                                   absl::StrCat(task.first, ":", task.last),
                                   "--output",
                                   work};
  if (spec.takes_calibration && !plan.options.calibration.empty()) {
    argv.insert(argv.end(), {"--calibration", plan.options.calibration});
  }
  const auto args = plan.options.stage_args.find(task.stage);
  if (args != plan.options.stage_args.end()) argv.insert(argv.end(), args->second.begin(), args->second.end());
  STAGE_RETURN_IF_ERROR(run(argv));
  STAGE_RETURN_IF_ERROR(InstallUnits(plan, task, work, stale));
  fs::remove_all(work, ec);
  return absl::OkStatus();
}

}  // namespace

absl::Status RunGraphTask(const GraphPlan& plan, int index, int attempt, const StageRunner& run,
                          const std::string& run_id) {
  if (!run_id.empty() && run_id != plan.run_id) {
    return absl::FailedPreconditionError(absl::StrCat("task of run ", run_id, ", but ", plan.run_dir,
                                                      "/plan.json is run ", plan.run_id,
                                                      "'s: a job an earlier run left queued; not run"));
  }
  if (index < 0 || index >= static_cast<int>(plan.tasks.size())) {
    return absl::InvalidArgumentError(
        absl::StrCat("task ", index, " is not in ", plan.run_dir, "/plan.json (", plan.tasks.size(), " tasks)"));
  }
  const GraphTask& task = plan.tasks[index];
  const auto started = std::chrono::steady_clock::now();
  const double cpu_before = ProcessCpuSeconds();
  TaskStatus status;
  status.state = TaskState::kRunning;
  status.attempt = attempt;
  status.pid = getpid();
  status.host = HostName();
  status.log = LogPath(plan, task);
  const std::string status_path = StatusPath(plan, task);
  STAGE_RETURN_IF_ERROR(WriteTaskStatus(status_path, status));
  auto times = [&] {
    status.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    status.cpu_s = ProcessCpuSeconds() - cpu_before;
  };
  auto fail = [&](const absl::Status& s) {
    times();
    status.state = TaskState::kFailed;
    status.message = std::string(s.message());
    (void)WriteTaskStatus(status_path, status);
    return s;
  };
  // Its units looked at again now that the tasks before it have run: what they made may be what was there.
  std::vector<std::pair<internal::Unit, internal::UnitKey>> stale;
  const std::vector<internal::Unit> units = internal::UnitsOf(plan, task);
  auto keys = internal::TaskUnitKeys(plan, task, units);
  if (!keys.ok()) return fail(keys.status());
  for (size_t i = 0; i < units.size(); ++i) {
    if (internal::CompareManifest(plan, task, units[i], (*keys)[i]).empty()) {
      ++status.up_to_date;
    } else {
      stale.emplace_back(units[i], std::move((*keys)[i]));
    }
  }
  if (!stale.empty()) {
    // A per-frame stage's chunk runs whole (its frames are independent: the ones up to date come out the same).
    if (auto s = RunStale(plan, task, attempt, run, stale); !s.ok()) return fail(s);
    status.made = static_cast<int64_t>(stale.size());
  }
  // What earlier attempts of it left (a killed one's half-made units).
  std::error_code ec;
  const std::string prefix = plan.TaskName(task) + "-a";
  for (fs::directory_iterator it(plan.run_dir + "/work", ec), end; !ec && it != end; it.increment(ec)) {
    if (it->path().filename().string().rfind(prefix, 0) == 0) fs::remove_all(it->path(), ec);
  }
  times();
  status.state = TaskState::kDone;
  status.message = absl::StrCat(status.made, " unit(s) made, ", status.up_to_date, " up to date");
  return WriteTaskStatus(status_path, status);
}

}  // namespace stage::processing
