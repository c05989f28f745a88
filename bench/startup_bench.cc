// What a process of the stage costs to start: each program run with --help (it loads its libraries, registers its
// options and exits before any work), beside the bare floor of a process in the same run (/bin/true: fork, exec and the
// C library alone). A simulated stage starts dozens of processes (a node per camera and light node, a processing task
// per step of the graph), so what each one loads at its start is paid many times over. Prints, per program, the median
// wall time and CPU time (user + system, from wait4) of --runs starts, and the libraries the dynamic loader maps for
// it (its LD_TRACE_LOADED_OBJECTS listing); --json prints the same as JSON.
// Run: build/bin/startup_bench [--runs 21] [--programs stage-process,camera-node,...]
#include <fcntl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "bench_util.h"

namespace {

namespace fs = std::filesystem;
using stage::bench::Clock;
using stage::bench::Die;

constexpr char kName[] = "startup_bench";

struct Start {
  double wall_ms = 0;
  double cpu_ms = 0;
};

// One start of `path` with `args`, its output thrown away (or, with `trace_libraries`, read back into `*listing`).
Start RunOnce(const std::string& path, const std::vector<std::string>& args, bool trace_libraries = false,
              std::string* listing = nullptr) {
  int out[2];
  if (pipe(out) != 0) Die(kName, "pipe failed");
  const auto t0 = Clock::now();
  const pid_t pid = fork();
  if (pid < 0) Die(kName, "fork failed");
  if (pid == 0) {
    const int null = open("/dev/null", O_WRONLY);
    dup2(trace_libraries ? out[1] : null, STDOUT_FILENO);
    dup2(null, STDERR_FILENO);
    close(out[0]);
    if (trace_libraries) setenv("LD_TRACE_LOADED_OBJECTS", "1", 1);
    std::vector<char*> argv;
    argv.push_back(const_cast<char*>(path.c_str()));
    for (const std::string& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    execv(path.c_str(), argv.data());
    _exit(127);
  }
  close(out[1]);
  std::string text;
  char buffer[4096];
  for (ssize_t n; (n = read(out[0], buffer, sizeof buffer)) > 0;) text.append(buffer, static_cast<size_t>(n));
  close(out[0]);
  int status = 0;
  rusage usage{};
  if (wait4(pid, &status, 0, &usage) != pid) Die(kName, "wait4 failed for " + path);
  const auto t1 = Clock::now();
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    Die(kName, absl::StrFormat("%s %s did not exit 0 (status %d)", path, absl::StrJoin(args, " "), status));
  }
  if (listing != nullptr) *listing = std::move(text);
  auto ms = [](const timeval& t) { return t.tv_sec * 1e3 + t.tv_usec / 1e3; };
  return {stage::bench::Ms(t1 - t0), ms(usage.ru_utime) + ms(usage.ru_stime)};
}

struct Figures {
  std::string name;
  double wall_ms = 0, cpu_ms = 0;
  int libraries = 0;
};

// --runs starts of `path` (after one unmeasured start, which brings its files into the page cache).
Figures Measure(const std::string& name, const std::string& path, const std::vector<std::string>& args, int runs) {
  RunOnce(path, args);
  std::vector<double> wall, cpu;
  for (int i = 0; i < runs; ++i) {
    const Start s = RunOnce(path, args);
    wall.push_back(s.wall_ms);
    cpu.push_back(s.cpu_ms);
  }
  std::string listing;
  RunOnce(path, {}, /*trace_libraries=*/true, &listing);
  int libraries = 0;
  for (absl::string_view line : absl::StrSplit(listing, '\n', absl::SkipWhitespace())) {
    // "libfoo.so.1 => /usr/lib/... (0x...)", the loader itself and the kernel's vDSO too: every object mapped.
    libraries += line.find("(0x") != absl::string_view::npos ? 1 : 0;
  }
  return {name, stage::bench::Median(wall), stage::bench::Median(cpu), libraries};
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "The start of the stage's programs (each run with --help) beside a bare process (/bin/true) in the same run: "
      "median wall and CPU time, and the libraries the loader maps",
      kName};
  int runs = 21;
  std::string programs = "stage-process,processing-worker,camera-node,light-node,stage-controller,stagectl,stage-sim";
  std::string bin_dir;
  bool json = false;
  app.add_option("--runs", runs, "Measured starts of each program (the median is printed)")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  app.add_option("--programs", programs, "Programs to start, comma-separated")->capture_default_str();
  app.add_option("--bin-dir", bin_dir, "Where the programs are (default: this benchmark's own directory)");
  app.add_flag("--json", json, "Print the figures as JSON");
  CLI11_PARSE(app, argc, argv);
  if (bin_dir.empty()) bin_dir = fs::read_symlink("/proc/self/exe").parent_path().string();

  std::vector<Figures> figures;
  figures.push_back(Measure("/bin/true (baseline)", "/bin/true", {}, runs));
  for (absl::string_view name : absl::StrSplit(programs, ',', absl::SkipWhitespace())) {
    const std::string program(name);
    const std::string path = (fs::path(bin_dir) / program).string();
    if (access(path.c_str(), X_OK) != 0) {
      Die(kName, absl::StrFormat("--programs: \"%s\" is not an executable (built? see --bin-dir)", path));
    }
    std::fprintf(stderr, "%s: %s...\n", kName, program.c_str());
    figures.push_back(Measure(program, path, {"--help"}, runs));
  }

  const Figures& floor = figures.front();
  if (json) {
    std::vector<std::string> rows;
    for (const Figures& f : figures) {
      rows.push_back(absl::StrFormat(R"({"program": "%s", "wall_ms": %.2f, "cpu_ms": %.2f, "libraries": %d})", f.name,
                                     f.wall_ms, f.cpu_ms, f.libraries));
    }
    std::printf("{\"runs\": %d, \"programs\": [%s]}\n", runs, absl::StrJoin(rows, ", ").c_str());
    return 0;
  }
  std::printf("starts of each program with --help, median of %d (the baseline first, in the same run):\n", runs);
  std::printf("  %-22s %10s %10s %10s %10s\n", "program", "wall ms", "x floor", "CPU ms", "libraries");
  for (const Figures& f : figures) {
    std::printf("  %-22s %10.1f %10.1f %10.1f %10d\n", f.name.c_str(), f.wall_ms, f.wall_ms / floor.wall_ms, f.cpu_ms,
                f.libraries);
  }
  return 0;
}
