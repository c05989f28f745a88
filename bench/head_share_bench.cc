// Memory of a user's head across the processes of a stage: N processes (a stage's camera nodes) each load the same
// head asset (2048 x 2048 maps by default, as a scan's), once sharing the decoded maps through the cache file they all
// map, and as the baseline in the same run each decoding its own copy (no cache directory). Prints, per run, the sum of
// the processes' proportional set size (PSS: a page shared by k processes counts 1/k in each) and of their resident
// size, and the time the slowest process took to load.
// Run: build/bin/head_share_bench [--processes 27] [--size 2048]
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_format.h"
#include "stage/sim/head.h"

namespace {

namespace fs = std::filesystem;

// A closed UV sphere of head size with texture coordinates, and maps of `size` texels (16-bit PGM/PPM, noisy so that
// no image compresses away).
stage::sim::HeadAssetFiles WriteAsset(const std::string& dir, int size) {
  fs::create_directories(dir);
  std::ofstream obj(dir + "/neutral.obj");
  constexpr int kRings = 100, kSegments = 200;
  for (int r = 0; r <= kRings; ++r) {
    for (int s = 0; s <= kSegments; ++s) {
      const double th = M_PI * r / kRings, ph = 2 * M_PI * s / kSegments;
      obj << absl::StrFormat("v %.4f %.4f %.4f\nvt %.5f %.5f\n", 90 * std::sin(th) * std::sin(ph), 100 * std::cos(th),
                             90 * std::sin(th) * std::cos(ph), static_cast<double>(s) / kSegments,
                             1 - static_cast<double>(r) / kRings);
    }
  }
  auto at = [](int r, int s) { return r * (kSegments + 1) + s + 1; };
  for (int r = 0; r < kRings; ++r) {
    for (int s = 0; s < kSegments; ++s) {
      const int a = at(r, s), b = at(r + 1, s), c = at(r + 1, s + 1), e = at(r, s + 1);
      obj << absl::StrFormat("f %d/%d %d/%d %d/%d\nf %d/%d %d/%d %d/%d\n", a, a, b, b, c, c, a, a, c, c, e, e);
    }
  }
  std::mt19937 rng(1);
  std::normal_distribution<float> noise(0, 0.05f);
  auto image = [&](const std::string& name, int channels, std::vector<float> base) {
    std::ofstream out(dir + "/" + name, std::ios::binary);
    out << (channels == 3 ? "P6" : "P5") << "\n" << size << " " << size << "\n65535\n";
    std::string row(static_cast<size_t>(size) * channels * 2, '\0');
    for (int y = 0; y < size; ++y) {
      for (size_t i = 0; i < row.size() / 2; ++i) {
        const float v = std::clamp(base[i % static_cast<size_t>(channels)] + noise(rng), 0.f, 1.f);
        const auto q = static_cast<uint16_t>(v * 65535);
        row[2 * i] = static_cast<char>(q >> 8);
        row[2 * i + 1] = static_cast<char>(q & 0xff);
      }
      out << row;
    }
  };
  image("albedo.ppm", 3, {0.6f, 0.45f, 0.35f});
  image("specular.pgm", 1, {0.3f});
  image("roughness.pgm", 1, {0.35f});
  image("normal.ppm", 3, {0.5f, 0.5f, 1.0f});
  stage::sim::HeadAssetFiles files;
  files.neutral_obj = dir + "/neutral.obj";
  files.albedo = dir + "/albedo.ppm";
  files.specular = dir + "/specular.pgm";
  files.roughness = dir + "/roughness.pgm";
  files.normal = dir + "/normal.ppm";
  return files;
}

long SmapsKb(pid_t pid, const std::string& field) {
  std::ifstream in(absl::StrFormat("/proc/%d/smaps_rollup", pid));
  std::string name;
  long kb = 0;
  while (in >> name) {
    if (name == field + ":") {
      in >> kb;
      return kb;
    }
    std::string rest;
    std::getline(in, rest);
  }
  return 0;
}

struct Run {
  long pss_mib = 0, rss_mib = 0;
  double slowest_s = 0;
  int own_copies = 0;
};

// `processes` children load the asset (with `cache_dir` as FASTAGE_CACHE_DIR), each touching every texel once (as a
// render does), then wait; their memory is read, and they are ended by pid.
Run LoadIn(int processes, const stage::sim::HeadAssetFiles& files, const std::string& cache_dir) {
  setenv("FASTAGE_CACHE_DIR", cache_dir.c_str(), 1);
  std::vector<pid_t> children;
  std::vector<int> reports;
  for (int i = 0; i < processes; ++i) {
    int fds[2];
    if (pipe(fds) != 0) std::exit(1);
    const pid_t pid = fork();
    if (pid == 0) {
      close(fds[0]);
      const auto t = std::chrono::steady_clock::now();
      auto head = stage::sim::HeadModel::FromAsset(files);
      if (!head.ok()) _exit(3);
      float sum = 0;
      for (float u = 0; u < 1; u += 1.0f / 1024) {
        for (float v = 0; v < 1; v += 1.0f / 1024) sum += (*head)->Surface({u, v}, 0, {}).material.albedo.x();
      }
      const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
      const char own = (*head)->maps_origin() == "decoded" ? 1 : 0;
      const char line[2] = {own, static_cast<char>(sum > 0)};
      if (write(fds[1], line, 2) != 2 || write(fds[1], &s, sizeof s) != sizeof s) _exit(4);
      pause();
      _exit(0);
    }
    close(fds[1]);
    children.push_back(pid);
    reports.push_back(fds[0]);
  }
  Run run;
  for (size_t i = 0; i < children.size(); ++i) {
    char line[2];
    double s = 0;
    if (read(reports[i], line, 2) != 2 || read(reports[i], &s, sizeof s) != sizeof s) {
      std::fprintf(stderr, "head_share_bench: a loader failed\n");
      std::exit(1);
    }
    run.own_copies += line[0];
    run.slowest_s = std::max(run.slowest_s, s);
  }
  for (pid_t pid : children) {
    run.pss_mib += SmapsKb(pid, "Pss") / 1024;
    run.rss_mib += SmapsKb(pid, "Rss") / 1024;
  }
  for (size_t i = 0; i < children.size(); ++i) {
    kill(children[i], SIGKILL);
    waitpid(children[i], nullptr, 0);
    close(reports[i]);
  }
  return run;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Memory of one head asset loaded by a stage's processes: shared decoded maps vs a copy each",
               "head_share_bench"};
  int processes = 27, size = 2048;
  app.add_option("--processes", processes, "Processes that load it (a stage's camera nodes)")->capture_default_str();
  app.add_option("--size", size, "Texels across each map")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  const std::string dir = fs::temp_directory_path() / absl::StrFormat("head-share-bench-%d", getpid());
  const auto files = WriteAsset(dir + "/asset", size);
  const Run shared = LoadIn(processes, files, dir + "/cache");
  const Run own = LoadIn(processes, files, "/proc/no-cache-here");  // baseline: every process decodes its own
  fs::remove_all(dir);
  std::printf("head asset with %dx%d maps, %d processes each loading it and touching every texel:\n", size, size,
              processes);
  std::printf("  %-34s PSS sum %6ld MiB  RSS sum %6ld MiB  slowest load %.2f s (%d own copies)\n",
              "shared decoded maps (cache file)", shared.pss_mib, shared.rss_mib, shared.slowest_s, shared.own_copies);
  std::printf("  %-34s PSS sum %6ld MiB  RSS sum %6ld MiB  slowest load %.2f s (%d own copies)\n",
              "baseline: a decoded copy each", own.pss_mib, own.rss_mib, own.slowest_s, own.own_copies);
  return 0;
}
