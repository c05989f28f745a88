// Scheduled-trigger delivery to 27 camera-node processes on loopback, every camera triggered in every slot at
// 912 Hz: how far ahead of its time each trigger reaches its node (lead at arrival; p0.01 is the worst margin), and
// how many were fired, late or missed. Beside it, in the same run and interleaved with it, the naive baseline that
// sends each trigger at its own time ("fire now"). Goal (issue #3): no trigger later than its time at the default
// lead of 20 slots.
// Run: build/bin/trigger_delivery_bench [--slots 10000] [--rounds 5] [--nodes 27]
#include <google/protobuf/util/json_util.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <map>
#include <thread>

#include "CLI/CLI.hpp"
#include "stage/common/file_util.h"
#include "stage/common/rig.h"
#include "stage/common/subprocess.h"
#include "stage/timing/schedule.h"
#include "stage/timing/timing_tool.h"
#include "stage/timing/trigger_scheduler.h"
#include "trigger_streamer.h"

namespace {

struct Totals {
  std::vector<int64_t> leads;
  uint64_t received = 0, fired = 0, late = 0, missed = 0, failed_streams = 0;
  int64_t max_fire_late = 0;
  std::string warning;
};

int64_t Percentile(std::vector<int64_t>& v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  size_t i = static_cast<size_t>(p / 100.0 * static_cast<double>(v.size() - 1) + 0.5);
  return v[std::min(i, v.size() - 1)];
}

void Fail(const std::string& what) {
  std::fprintf(stderr, "trigger_delivery_bench: %s\n", what.c_str());
  std::exit(1);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Scheduled-trigger delivery to camera-node processes on loopback: lead at arrival and late/missed "
      "counts at the rig's trigger lead, next to sending each trigger at its own time.",
      "trigger_delivery_bench"};
  int64_t slots = 10000;
  int rounds = 5;
  int nodes = 27;
  uint32_t priority = 0;
  std::string bin_dir = "build/bin";
  app.add_option("--slots", slots, "Slots per mode in all")->capture_default_str()->check(CLI::Range(100, 1000000));
  app.add_option("--rounds", rounds, "Rounds the slots are split into, modes interleaved")->capture_default_str();
  app.add_option("--nodes", nodes, "Camera nodes (the shipped rig's cameras, in order)")
      ->capture_default_str()
      ->check(CLI::Range(1, 27));
  app.add_option("--bin-dir", bin_dir, "Where camera-node is")->capture_default_str();
  app.add_option("--priority", priority,
                 "SCHED_FIFO priority of the nodes' firing threads (timing.trigger_realtime_priority); 0 = normal")
      ->capture_default_str()
      ->check(CLI::Range(0, 99));
  CLI11_PARSE(app, argc, argv);

  // The shipped rig with every camera on scheduled software triggers in every slot, small frames (the sim cameras
  // render each fired trigger; this measures delivery, not rendering).
  auto loaded = stage::LoadRig(stage::kBuiltinRigName);
  auto rig =
      stage::ApplyRigOverrides(*loaded, {"cameras[*].trigger.source=scheduled-software", "cameras[*].trigger.divider=1",
                                         "cameras[*].trigger.slot_phase=0", "cameras[*].frame_rate_hz=912",
                                         "cameras[*].readout_us=0", "cameras[*].max_frame_rate_hz=0",
                                         "cameras[*].backend=sim", "cameras[*].width=64", "cameras[*].height=32"});
  if (!rig.ok()) Fail(std::string(rig.status().message()));
  auto report = stage::timing::CheckTiming(*rig, {});
  if (!report.ok()) Fail(std::string(report.status().message()));
  const stage::v1::Schedule& schedule = report->schedule();

  char tmpl[] = "/tmp/fastage-trigger-bench.XXXXXX";
  const std::string dir = mkdtemp(tmpl);
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(rig->rig, &json, print);
  const std::string rig_path = dir + "/rig.json";
  if (auto s = stage::WriteFileAtomically(rig_path, json); !s.ok()) Fail(std::string(s.message()));

  std::vector<std::unique_ptr<stage::Subprocess>> processes;
  std::vector<stage::controller::TriggerTarget> targets;
  for (int i = 0; i < nodes; ++i) {
    const std::string id = rig->rig.cameras(i).id();
    const std::string port_file = dir + "/" + id + ".port";
    auto p = stage::Subprocess::Spawn(
        {.argv = {bin_dir + "/camera-node", "--config", rig_path, "--id", id, "--listen", "127.0.0.1:0", "--port-file",
                  port_file, "--ptp-uds", "none", "--log-level", "warn"},
         .stderr_path = dir + "/" + id + ".log"});
    if (!p.ok()) Fail(std::string(p.status().message()));
    processes.push_back(std::move(*p));
    stage::controller::TriggerTarget t;
    t.id = id;
    t.timing = *stage::timing::FindCameraTiming(schedule, id);
    targets.push_back(t);
  }
  for (int i = 0; i < nodes; ++i) {
    const std::string port_file = dir + "/" + targets[i].id + ".port";
    for (int tries = 0; !std::filesystem::exists(port_file); ++tries) {
      if (tries > 3000 || processes[i]->Poll()) Fail("camera-node " + targets[i].id + " did not start; see " + dir);
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    targets[i].address = *stage::ReadFileToString(port_file);
  }

  const int64_t lead_ns = schedule.trigger_lead_slots() * 1'000'000'000LL / schedule.time_base().slot_rate_hz();
  std::map<int64_t, Totals> totals;  // by lead
  const int64_t per_round = slots / rounds;
  for (int r = 0; r < rounds; ++r) {
    for (int64_t lead : {lead_ns, int64_t{0}}) {
      stage::controller::TriggerStreamOptions options;
      options.take_id = "bench";
      options.slot_rate_hz = schedule.time_base().slot_rate_hz();
      options.t0_unix_ns = stage::timing::TriggerScheduler::NowNs() + 300'000'000;
      options.slot_count = per_round;
      options.lead_ns = lead;
      options.report_leads = true;
      options.realtime_priority = priority;
      stage::controller::TriggerStreamer streamer(options, targets);
      streamer.Start();
      Totals& t = totals[lead];
      for (auto& result : streamer.Wait()) {
        if (!result.ok()) {
          ++t.failed_streams;
          std::fprintf(stderr, "stream failed: %s\n", std::string(result.status().message()).c_str());
          continue;
        }
        t.received += result->received();
        t.fired += result->fired();
        t.late += result->late();
        t.missed += result->missed();
        t.max_fire_late = std::max(t.max_fire_late, result->max_fire_late_ns());
        t.leads.insert(t.leads.end(), result->lead_ns().begin(), result->lead_ns().end());
        if (!result->warning().empty()) t.warning = result->warning();
      }
    }
    std::fprintf(stderr, "round %d of %d done\n", r + 1, rounds);
  }
  for (auto& p : processes) p->Terminate(std::chrono::milliseconds(3000));
  std::filesystem::remove_all(dir);

  std::printf(
      "scheduled triggers to %d camera nodes on loopback, every camera in every slot at %u Hz, %lld slots per "
      "mode in %d interleaved rounds (%u cores); firing threads %s\n",
      nodes, schedule.time_base().slot_rate_hz(), static_cast<long long>(per_round * rounds), rounds,
      std::thread::hardware_concurrency(),
      priority > 0 ? ("SCHED_FIFO " + std::to_string(priority)).c_str() : "normal scheduling");
  std::printf("%-34s %10s %10s %10s %9s %9s %7s %7s %9s %12s\n", "mode", "lead p0.01", "lead p1", "lead p50",
              "triggers", "fired", "late", "missed", "after due", "max fire late");
  for (auto& [lead, t] : totals) {
    int64_t after_due = 0;
    for (int64_t l : t.leads) after_due += l < 0;
    const std::string name = lead > 0 ? "streamed ahead (lead " + std::to_string(schedule.trigger_lead_slots()) +
                                            " slots = " + std::to_string(lead / 1000) + " us)"
                                      : "baseline: sent at fire time";
    std::printf("%-34s %8.3fms %8.3fms %8.3fms %9llu %9llu %7llu %7llu %9lld %10.1fus\n", name.c_str(),
                Percentile(t.leads, 0.01) / 1e6, Percentile(t.leads, 1) / 1e6, Percentile(t.leads, 50) / 1e6,
                static_cast<unsigned long long>(t.received), static_cast<unsigned long long>(t.fired),
                static_cast<unsigned long long>(t.late), static_cast<unsigned long long>(t.missed),
                static_cast<long long>(after_due), t.max_fire_late / 1e3);
    if (!t.warning.empty()) std::printf("  node: %s\n", t.warning.c_str());
    if (t.failed_streams > 0) std::printf("  %llu streams failed\n", static_cast<unsigned long long>(t.failed_streams));
  }
  std::printf(
      "late: arrived in time but not fired within the camera's late slack; missed: arrived after it; after "
      "due: arrived after its time\n");
  return 0;
}
