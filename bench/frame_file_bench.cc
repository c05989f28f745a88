// Recording throughput of a frame file (the HDF5 writer a camera node records with: SWMR, every frame flushed, space
// reserved ahead), and of the camera node's whole recording path (TakeRecorder, live as a machine-vision camera
// records: each frame tagged by its timestamp on the camera's thread, queued, written on the writer thread, the take
// accounted at the end), next to their baseline in the same run: plain sequential write() of the same bytes to a
// file in the same directory. All end with fsync, so all count the disk, not the page cache. Goal: >= 0.8x the
// baseline.
// Run: build/bin/frame_file_bench [--dir DIR] [--frames N] [--width W --height H --bytes-per-pixel B]
#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "recorder.h"
#include "stage/storage/frame_file.h"

namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) { return std::chrono::duration<double>(Clock::now() - since).count(); }

// Plain write() of every frame, then fsync: what the disk gives a writer that does nothing else.
// Every writer takes its frames from a pool of kPool buffers of the same bytes, as a camera's frames come from its
// buffer pool (never hot in the cache).
constexpr int kPool = 20;
using Buffers = std::vector<std::vector<uint8_t>>;

double PlainWrite(const std::string& path, const Buffers& buffers, int frames) {
  std::filesystem::remove(path);  // a new file each round, as the frame file is
  const auto start = Clock::now();
  const int fd = open(path.c_str(), O_CREAT | O_TRUNC | O_WRONLY, 0644);
  if (fd < 0) {
    std::perror(path.c_str());
    std::exit(1);
  }
  for (int i = 0; i < frames; ++i) {
    const std::vector<uint8_t>& frame = buffers[static_cast<size_t>(i) % buffers.size()];
    size_t done = 0;
    while (done < frame.size()) {
      const ssize_t n = write(fd, frame.data() + done, frame.size() - done);
      if (n <= 0) {
        std::perror("write");
        std::exit(1);
      }
      done += static_cast<size_t>(n);
    }
  }
  fsync(fd);
  close(fd);
  return Seconds(start);
}

double FrameFile(const std::string& path, const Buffers& buffers, int frames,
                 const stage::storage::FrameFileInfo& info) {
  std::filesystem::remove(path);
  const auto start = Clock::now();
  auto writer = stage::storage::FrameFileWriter::Create(path, info);
  if (!writer.ok()) {
    std::fprintf(stderr, "%s\n", std::string(writer.status().message()).c_str());
    std::exit(1);
  }
  for (int i = 0; i < frames; ++i) {
    stage::storage::FrameRecord r;
    r.frame_id = static_cast<uint64_t>(i);
    r.slot = i;
    r.pattern = i % 38;
    if (auto s = (*writer)->Append(r, buffers[static_cast<size_t>(i) % buffers.size()]); !s.ok()) {
      std::fprintf(stderr, "%s\n", std::string(s.message()).c_str());
      std::exit(1);
    }
  }
  if (auto s = (*writer)->Close(); !s.ok()) std::fprintf(stderr, "%s\n", std::string(s.message()).c_str());
  const int fd = open(path.c_str(), O_RDONLY);
  fsync(fd);
  close(fd);
  return Seconds(start);
}

// The camera node's recorder, live: frames come on this (the camera's) thread with timestamps on the take's slots;
// the caller waits while kPool - 4 are queued (a buffer is reused only once the recorder let go of it), so this
// measures what it sustains.
double Recorder(const std::string& path, const Buffers& buffers, int frames,
                const stage::storage::FrameFileInfo& info) {
  std::filesystem::remove(path);
  constexpr int kQueued = kPool - 4;
  stage::camera::TakePlan plan;
  plan.path = path;
  plan.info = info;
  plan.slots = frames;
  plan.first_frame_id = 0;
  // A camera's buffer pool: the driver fills its buffers, so filling them is not the recorder's work.
  std::vector<std::shared_ptr<stage::camera::Frame>> pool(buffers.size());
  for (size_t i = 0; i < pool.size(); ++i) {
    pool[i] = std::make_shared<stage::camera::Frame>();
    pool[i]->width = info.width;
    pool[i]->height = info.height;
    pool[i]->data = buffers[i];
  }
  const auto start = Clock::now();
  auto recorder = stage::camera::TakeRecorder::Start(plan);
  if (!recorder.ok()) {
    std::fprintf(stderr, "%s\n", std::string(recorder.status().message()).c_str());
    std::exit(1);
  }
  for (int i = 0; i < frames; ++i) {
    while ((*recorder)->frames_received() - (*recorder)->frames_written() >= kQueued) {
      std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
    // The buffer is free again: at most kQueued frames are still held by the recorder.
    auto& f = pool[static_cast<size_t>(i) % pool.size()];
    f->frame_id = static_cast<uint64_t>(i);
    f->device_timestamp_ns = i * plan.slot_ns;
    (*recorder)->OnFrame(f);
  }
  const stage::camera::TakeRecording r = (*recorder)->Finish();
  if (r.frames_written != frames) {
    std::fprintf(stderr, "recorder: %lld of %d frames written: %s\n", static_cast<long long>(r.frames_written), frames,
                 r.error.c_str());
    std::exit(1);
  }
  const int fd = open(path.c_str(), O_RDONLY);
  fsync(fd);
  close(fd);
  return Seconds(start);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Frame file recording throughput against plain sequential writes of the same bytes (same run, same "
      "directory; both end with fsync)"};
  std::string dir = std::filesystem::temp_directory_path().string();
  int frames = 100;
  stage::storage::FrameFileInfo info;
  info.camera_id = "mv-01";
  info.width = 2592;
  info.height = 2048;
  info.bytes_per_pixel = 1;
  info.pixel_format = "BayerRG8";
  int rounds = 3;
  app.add_option("--dir", dir, "Where to write (the disk to measure)")->capture_default_str();
  app.add_option("--frames", frames, "Frames per run")->capture_default_str()->check(CLI::Range(1, 100000));
  app.add_option("--width", info.width, "Frame width")->capture_default_str();
  app.add_option("--height", info.height, "Frame height")->capture_default_str();
  app.add_option("--bytes-per-pixel", info.bytes_per_pixel, "1 or 2")->capture_default_str();
  app.add_option("--rounds", rounds, "Alternating rounds of each; the best of each is reported")
      ->capture_default_str()
      ->check(CLI::Range(1, 20));
  CLI11_PARSE(app, argc, argv);

  std::vector<uint8_t> frame(static_cast<size_t>(info.width) * info.height * info.bytes_per_pixel);
  for (size_t i = 0; i < frame.size(); ++i) frame[i] = static_cast<uint8_t>(i * 131 + (i >> 12));
  const double mb = static_cast<double>(frame.size()) * frames / 1e6;
  const Buffers buffers(kPool, frame);
  const std::string plain = dir + "/frame_file_bench.raw", h5 = dir + "/frame_file_bench.h5",
                    node = dir + "/frame_file_bench_node.h5";
  double best_plain = 1e30, best_h5 = 1e30, best_node = 1e30;
  for (int r = 0; r < rounds; ++r) {
    best_plain = std::min(best_plain, PlainWrite(plain, buffers, frames));
    best_h5 = std::min(best_h5, FrameFile(h5, buffers, frames, info));
    best_node = std::min(best_node, Recorder(node, buffers, frames, info));
  }
  std::filesystem::remove(plain);
  std::filesystem::remove(h5);
  std::filesystem::remove(node);
  std::printf("frame_file_bench: %d frames of %ux%u x %u B (%.0f MB) in %s, best of %d\n", frames, info.width,
              info.height, info.bytes_per_pixel, mb, dir.c_str(), rounds);
  std::printf("  baseline: plain write() + fsync   %8.1f MB/s\n", mb / best_plain);
  std::printf("  frame file (HDF5, SWMR, flushed)  %8.1f MB/s   = %.2fx the baseline (goal >= 0.8x)\n", mb / best_h5,
              best_plain / best_h5);
  std::printf("  camera node recorder (live)       %8.1f MB/s   = %.2fx the baseline (goal >= 0.8x)\n", mb / best_node,
              best_plain / best_node);
  return 0;
}
