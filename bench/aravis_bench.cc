// The camera node's Aravis backend against Aravis's own streaming tool, in one run, on one fake GigE Vision camera
// (arv-fake-gv-camera-0.8, a separate process) with the same settings: arv-camera-test-0.8 streams it for --seconds,
// then AravisCameraDevice (zero-copy delivery to a sink that touches each frame, as the recorder's queue does) for
// as long, alternating --rounds times. Prints frames/s and CPU seconds per frame (the whole receiving process: open,
// configure, stream) for each, and their ratios. Goal (issue 7): frames/s >= 0.95x and CPU per frame <= 1.2x of
// arv-camera-test. Runs in a network namespace of its own when it can (as root), else on the host's loopback.
#include <sched.h>
#include <signal.h>
#include <spawn.h>
#include <sys/resource.h>
#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_format.h"
#include "aravis_camera_device.h"

extern "C" char** environ;

namespace {



double CpuSeconds(const rusage& r) {
  return static_cast<double>(r.ru_utime.tv_sec + r.ru_stime.tv_sec) +
         static_cast<double>(r.ru_utime.tv_usec + r.ru_stime.tv_usec) * 1e-6;
}

// Runs argv, stdout to `out_path`; returns its CPU seconds (wait4), or -1.
double RunMeasured(const std::vector<std::string>& argv, const std::string& out_path) {
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, out_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&actions, 2, "/dev/null", O_WRONLY, 0);
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  pid_t pid;
  if (posix_spawnp(&pid, args[0], &actions, nullptr, args.data(), environ) != 0) return -1;
  posix_spawn_file_actions_destroy(&actions);
  int status = 0;
  rusage usage{};
  if (wait4(pid, &status, 0, &usage) != pid) return -1;
  return CpuSeconds(usage);
}

struct Result {
  double fps = 0;
  double cpu_per_frame = 0;
  uint64_t frames = 0;
};

// arv-camera-test prints a line a second: "  NN frame/s - X MiB/s - E errors" (whole frames); the first (start-up)
// is left out. -a: it sizes its socket buffer to the payload, as the node does (without, every frame loses packets).
Result ArvCameraTest(const std::string& name, const std::string& hz, int w, int h, int seconds,
                     const std::string& out_path) {
  const double cpu = RunMeasured({"arv-camera-test-0.8", "-n", name, "-f", hz, "-w", std::to_string(w), "-h",
                                  std::to_string(h), "-i", "9000", "--no-packet-socket", "-r", "-a",
                                  "--duration=" + std::to_string(seconds)},
                                 out_path);
  std::ifstream in(out_path);
  std::string line;
  std::vector<double> per_second;
  const std::regex re(R"(^\s*(\d+) frames?/s)");
  while (std::getline(in, line)) {
    std::smatch m;
    if (std::regex_search(line, m, re)) per_second.push_back(std::stod(m[1]));
  }
  Result r;
  if (per_second.size() < 2 || cpu < 0) return r;
  double frames = 0;
  for (size_t i = 1; i < per_second.size(); ++i) frames += per_second[i];
  r.fps = frames / static_cast<double>(per_second.size() - 1);
  for (double f : per_second) r.frames += static_cast<uint64_t>(f);
  r.cpu_per_frame = r.frames > 0 ? cpu / static_cast<double>(r.frames) : 0;
  return r;
}

class CountingSink : public stage::camera::FrameSink {
 public:
  void OnFrame(std::shared_ptr<const stage::camera::Frame> frame) override {
    const auto px = frame->pixels();
    if (!px.empty()) checksum_.fetch_add(px[px.size() / 2]);
    frames_.fetch_add(1);
    if (frame->incomplete.empty()) complete_.fetch_add(1);
  }
  std::atomic<uint64_t> frames_{0}, complete_{0}, checksum_{0};
};

Result Node(const std::string& address, double hz, int w, int h, int seconds) {
  rusage before{}, after{};
  getrusage(RUSAGE_SELF, &before);
  Result r;
  auto device = stage::camera::AravisCameraDevice::Open("bench", address);
  if (!device.ok()) {
    std::cerr << "aravis_bench: " << device.status() << "\n";
    return r;
  }
  stage::camera::CameraSettings s;
  s.width = w;
  s.height = h;
  s.pixel_format = "Mono8";
  s.frame_rate_hz = hz;
  s.exposure_us = 1000;
  s.trigger = stage::camera::TriggerMode::kFreeRun;
  s.packet_size = 9000;
  s.packet_resend = false;
  s.packet_socket = false;
  if (auto st = (*device)->Configure(s); !st.ok()) {
    std::cerr << "aravis_bench: " << st << "\n";
    return r;
  }
  CountingSink sink;
  if (auto st = (*device)->Start(&sink); !st.ok()) {
    std::cerr << "aravis_bench: " << st << "\n";
    return r;
  }
  // As arv-camera-test: the first second is start-up; frames/s over the rest.
  std::this_thread::sleep_for(std::chrono::seconds(1));
  const uint64_t at_1s = sink.complete_.load();
  const auto t1 = std::chrono::steady_clock::now();
  std::this_thread::sleep_for(std::chrono::seconds(seconds - 1));
  const uint64_t at_end = sink.complete_.load();
  const double span = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
  (void)(*device)->Stop();
  device->reset();
  getrusage(RUSAGE_SELF, &after);
  r.frames = sink.frames_.load();
  r.fps = static_cast<double>(at_end - at_1s) / span;
  r.cpu_per_frame = r.frames > 0 ? (CpuSeconds(after) - CpuSeconds(before)) / static_cast<double>(r.frames) : 0;
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Benchmarks the camera node's Aravis backend against arv-camera-test-0.8 on a fake GigE Vision camera",
               "aravis_bench"};
  int width = 1024, height = 1024, seconds = 6, rounds = 2;
  double hz = 200;
  app.add_option("--width", width, "Image width")->capture_default_str()->check(CLI::Range(16, 2048));
  app.add_option("--height", height, "Image height")->capture_default_str()->check(CLI::Range(16, 2048));
  app.add_option("--hz", hz, "Frame rate asked of the fake camera")->capture_default_str()->check(CLI::Range(1.0, 2000.0));
  app.add_option("--seconds", seconds, "Streaming time of each run")->capture_default_str()->check(CLI::Range(3, 600));
  app.add_option("--rounds", rounds, "Runs of each, alternating")->capture_default_str()->check(CLI::Range(1, 20));
  CLI11_PARSE(app, argc, argv);

  std::string where = "the host's loopback";
  if (unshare(CLONE_NEWNET) == 0 && std::system("ip link set lo up") == 0) where = "a network namespace of its own";
  const std::string address = "127.0.0.1";
  const std::string serial = "BENCH";
  pid_t fake;
  {
    std::vector<std::string> a = {"arv-fake-gv-camera-0.8", "-i", address, "-s", serial};
    std::vector<char*> args;
    for (auto& s : a) args.push_back(s.data());
    args.push_back(nullptr);
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
    posix_spawn_file_actions_addopen(&actions, 2, "/dev/null", O_WRONLY, 0);
    if (posix_spawnp(&fake, args[0], &actions, nullptr, args.data(), environ) != 0) {
      std::cerr << "aravis_bench: cannot start arv-fake-gv-camera-0.8 (scripts/bootstrap installs aravis-tools)\n";
      return 1;
    }
    posix_spawn_file_actions_destroy(&actions);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  const std::string name = "Aravis-Fake-" + serial;  // arv-camera-test finds it by its Aravis id
  std::cout << absl::StrFormat(
      "aravis_bench: fake GigE Vision camera at %s (%s), %dx%d Mono8 at %g Hz asked, 9000-byte packets, no resend, no "
      "packet socket, socket buffer sized to frames; whole frames counted; %d s per run, %d round(s)\n",
      address, where, width, height, hz, seconds, rounds);
  std::vector<Result> tool, node;
  char tmpl[] = "/tmp/aravis-bench-XXXXXX";
  const int fd = mkstemp(tmpl);
  if (fd >= 0) close(fd);
  for (int i = 0; i < rounds; ++i) {
    tool.push_back(ArvCameraTest(name, absl::StrFormat("%g", hz), width, height, seconds, tmpl));
    std::this_thread::sleep_for(std::chrono::milliseconds(3500));  // the fake drops the last controller
    node.push_back(Node(address, hz, width, height, seconds));
    std::this_thread::sleep_for(std::chrono::milliseconds(3500));
    std::cout << absl::StrFormat(
        "  round %d: arv-camera-test %7.1f frames/s %8.3f ms CPU/frame | camera-node %7.1f frames/s %8.3f ms CPU/frame\n",
        i + 1, tool.back().fps, tool.back().cpu_per_frame * 1e3, node.back().fps, node.back().cpu_per_frame * 1e3);
  }
  std::remove(tmpl);
  kill(fake, SIGTERM);
  waitpid(fake, nullptr, 0);
  auto median = [](std::vector<Result> v, auto field) {
    std::vector<double> x;
    for (const auto& r : v) x.push_back(r.*field);
    std::sort(x.begin(), x.end());
    return x[x.size() / 2];
  };
  const double tool_fps = median(tool, &Result::fps), node_fps = median(node, &Result::fps);
  const double tool_cpu = median(tool, &Result::cpu_per_frame), node_cpu = median(node, &Result::cpu_per_frame);
  if (tool_fps <= 0 || node_fps <= 0) {
    std::cerr << "aravis_bench: a run streamed nothing\n";
    return 1;
  }
  std::cout << absl::StrFormat("arv-camera-test-0.8: %7.1f frames/s, %.3f ms CPU per frame (median of %d)\n", tool_fps,
                               tool_cpu * 1e3, rounds);
  std::cout << absl::StrFormat("camera-node aravis:  %7.1f frames/s, %.3f ms CPU per frame (median of %d)\n", node_fps,
                               node_cpu * 1e3, rounds);
  std::cout << absl::StrFormat("ratio: frames/s %.3fx (goal >= 0.95x), CPU per frame %.3fx (goal <= 1.2x)\n",
                               node_fps / tool_fps, node_cpu / tool_cpu);
  return 0;
}
