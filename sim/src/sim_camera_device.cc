// Simulated camera device.
#include "stage/sim/sim_camera_device.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/string_view.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/sim/scene.h"
#include "stage/sim/world_client.h"
#include "stage/timing/time_base.h"

namespace stage::sim {

std::optional<int> SimBytesPerPixel(const std::string& f) {
  if (f == "Mono8" || f == "BayerRG8" || f == "BayerGR8" || f == "BayerGB8" || f == "BayerBG8") return 1;
  if (f == "Mono12" || f == "Mono16" || f == "BayerRG12" || f == "BayerRG16") return 2;
  if (f == "RGB8") return 3;
  return std::nullopt;
}

SimCameraDevice::SimCameraDevice(Clock* clock, std::string serial) : clock_(clock), serial_(std::move(serial)) {}

SimCameraDevice::~SimCameraDevice() { (void)Stop(); }

camera::CameraDescription SimCameraDevice::Describe() const { return {"sim", "FaStage", "SimCamera", serial_}; }

absl::Status SimCameraDevice::Configure(const camera::CameraSettings& s) {
  auto bad = [&](absl::string_view what) {
    return absl::InvalidArgumentError(absl::StrCat("sim camera ", serial_, ": ", what));
  };
  if (s.width == 0 || s.width > 16384 || s.height == 0 || s.height > 16384) {
    return bad(absl::StrFormat("size %ux%u is not within 1..16384 x 1..16384", s.width, s.height));
  }
  if (!SimBytesPerPixel(s.pixel_format)) {
    return bad(absl::StrCat("pixel format \"", s.pixel_format,
                            "\" is not supported (Mono8/12/16, BayerRG8/GR8/GB8/BG8/RG12/RG16, RGB8)"));
  }
  if (!(s.frame_rate_hz > 0 && s.frame_rate_hz <= 100000)) {
    return bad(absl::StrFormat("frame rate %g Hz is not within (0, 100000]", s.frame_rate_hz));
  }
  double period_us = 1e6 / s.frame_rate_hz;
  if (!(s.exposure_us > 0 && s.exposure_us < period_us)) {
    return bad(absl::StrFormat("exposure %g us is not within (0, %.3f) us, the frame period at %g Hz", s.exposure_us,
                               period_us, s.frame_rate_hz));
  }
  if (!(s.gain_db >= 0 && s.gain_db <= 48)) return bad(absl::StrFormat("gain %g dB is not within [0, 48]", s.gain_db));
  std::lock_guard<std::mutex> lock(mutex_);
  if (running_)
    return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": configure while acquiring"));
  settings_ = s;
  configured_ = true;
  return absl::OkStatus();
}

camera::CameraSettings SimCameraDevice::settings() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return settings_;
}

absl::Status SimCameraDevice::AttachWorld(SimCameraWorld world) {
  if (world.world == nullptr || world.renderer == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat("sim camera ", serial_, ": no world or renderer to attach to"));
  }
  if (world.divider == 0 || world.phase >= world.divider || world.exposure_ns <= 0 || world.buffer_frames < 1) {
    return absl::InvalidArgumentError(absl::StrCat("sim camera ", serial_, ": bad trigger plan (divider ",
                                                   world.divider, ", phase ", world.phase, ", exposure ",
                                                   world.exposure_ns, " ns, buffers ", world.buffer_frames, ")"));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  if (running_) return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": attach while acquiring"));
  world_ = std::move(world);
  return absl::OkStatus();
}

SimCameraWorldStats SimCameraDevice::world_stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

absl::Status SimCameraDevice::Start(camera::FrameSink* sink) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!configured_)
    return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": start before configure"));
  if (running_) return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": already acquiring"));
  if (world_) {
    if (settings_.trigger != camera::TriggerMode::kHardware) {
      return absl::FailedPreconditionError(
          absl::StrCat("sim camera ", serial_,
                       ": in the simulated world a camera is triggered by the world's trigger bus; "
                       "set its trigger source to hardware-line"));
    }
    auto device = world_->world->Join(serial_, -1);
    if (!device.ok()) return device.status();
    world_device_ = *device;
    sink_ = sink;
    running_ = true;
    jobs_.clear();
    stats_ = {};
    next_frame_id_ = 0;
    thread_ = std::thread([this, d = *device] { TriggerLoop(d); });
    render_thread_ = std::thread([this] { RenderLoop(); });
    return absl::OkStatus();
  }
  sink_ = sink;
  running_ = true;
  stopping_.store(false);
  pending_triggers_ = 0;
  next_frame_id_ = 0;
  thread_ = std::thread([this] { Run(); });
  return absl::OkStatus();
}

absl::Status SimCameraDevice::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!running_) return absl::OkStatus();
    running_ = false;
  }
  wake_.notify_all();
  jobs_changed_.notify_all();
  if (world_) {
    world_->world->Leave(world_device_);  // wakes the trigger thread
  } else {
    stopping_.store(true);  // a free-running acquisition sleeps on the clock until this is set
    clock_->Interrupt();
  }
  if (thread_.joinable()) thread_.join();
  if (render_thread_.joinable()) render_thread_.join();
  sink_ = nullptr;
  return absl::OkStatus();
}

namespace {

// The first slot >= `from` that fires under divider/phase, and how many fire in [from, to).
int64_t FirstFiring(int64_t from, int64_t divider, int64_t phase) {
  int64_t m = (phase - from) % divider;
  if (m < 0) m += divider;
  return from + m;
}
// A deterministic draw in [0, 1) for a fault decision: the seed, the camera, the slot and which fault.
double FaultDraw(uint64_t seed, const std::string& camera, int64_t slot, uint64_t which) {
  uint64_t h = Fnv1a64(camera, 1469598103934665603ull ^ seed);
  for (uint64_t v : {static_cast<uint64_t>(slot), which}) {
    h ^= v + 0x9e3779b97f4a7c15ull + (h << 6) + (h >> 2);
    h = (h ^ (h >> 31)) * 0xbf58476d1ce4e5b9ull;
  }
  return static_cast<double>(h >> 11) / static_cast<double>(1ull << 53);
}

int64_t CountFiring(int64_t from, int64_t to, int64_t divider, int64_t phase) {
  const int64_t first = FirstFiring(from, divider, phase);
  return first >= to ? 0 : (to - 1 - first) / divider + 1;
}

}  // namespace

void SimCameraDevice::ApplyFault(const v1::SimFault& fault) {
  SimCameraWorld& w = *world_;
  if (fault.has_miss_triggers()) w.miss_triggers = fault.miss_triggers();
  if (fault.has_drop_frames()) w.drop_frames = fault.drop_frames();
  if (fault.drop_slots_size() > 0) w.drop_slots = {fault.drop_slots().begin(), fault.drop_slots().end()};
  if (fault.has_clock_offset_us())
    w.clock_offset_ns = static_cast<int64_t>(std::llround(fault.clock_offset_us() * 1e3));
  if (fault.has_clock_drift_ppm()) w.clock_drift_ppm = fault.clock_drift_ppm();
  if (fault.has_crash_at_s()) w.crash_at_ns = static_cast<int64_t>(std::llround(fault.crash_at_s() * 1e9));
  Logger("sim")->warn("sim camera {}: fault injected: {}", serial_, fault.ShortDebugString());
}

void SimCameraDevice::TriggerLoop(int device) {
  SimCameraWorld& w = *world_;
  WorldClient* world = w.world;
  const bool lockstep = world->lockstep();
  auto base = timing::TimeBase::Create(world->slot_rate_hz());
  if (!base.ok()) {
    Logger("sim")->error("sim camera {}: {}", serial_, base.status().message());
    return;
  }
  const int64_t period = base->SlotStartNs(1);
  // Lockstep: the slots this camera lets the world run ahead of its trigger, so that the light its exposure needs
  // (up to the end of the exposure) is reported while it waits for its renderer.
  const int64_t ahead = (w.trigger_delay_ns + w.exposure_ns) / std::max<int64_t>(1, period) + 1;
  const int64_t d = w.divider, p = w.phase;
  // The trigger line is the bus divided from the first slot of each run (the sync generator restarts it at T0):
  // slot k of run r fires when (k - r.first) mod divider == phase.
  auto first_firing = [&](int64_t from, const WorldRun& r) {
    const int64_t at = r.first + FirstFiring(std::max(from, r.first) - r.first, d, p);
    return at < r.end ? at : r.end;  // none left in this run: wait for the next run's first edge
  };
  int64_t slot = p;
  while (true) {
    auto edge = world->WaitForEdge(device, slot);
    if (!edge) {
      std::lock_guard<std::mutex> lock(mutex_);
      if (running_) Logger("sim")->warn("sim camera {}: the world ended or let it go at slot {}", serial_, slot);
      break;
    }
    const int64_t k = edge->slot;
    const WorldRun& run = edge->run;
    const int64_t missed = CountFiring(std::max(slot, run.first) - run.first, k - run.first, d, p);
    std::unique_lock<std::mutex> lock(mutex_);
    if (!running_) break;
    stats_.missed_triggers += static_cast<uint64_t>(missed);
    for (const v1::SimFault& fault : edge->faults) ApplyFault(fault);
    if (w.crash_at_ns >= 0 && edge->time_ns >= w.crash_at_ns) {
      Logger("sim")->warn("sim camera {}: crashes at slot {} (fault)", serial_, k);
      lock.unlock();
      if (w.on_crash) w.on_crash();
      world->Leave(device);
      break;
    }
    if (first_firing(k, run) == k) {
      if (w.miss_triggers > 0 && FaultDraw(w.seed, serial_, k, 1) < w.miss_triggers) {
        ++stats_.missed_triggers;  // a fault: the trigger never reached the sensor
      } else if (!lockstep && static_cast<int>(jobs_.size()) >= w.buffer_frames) {
        ++stats_.missed_triggers;  // busy: every buffer holds a frame not yet read out
      } else {
        const int64_t start = edge->time_ns + w.trigger_delay_ns;
        // The camera's clock, and whether the frame is lost on the way out, as the faults are now.
        const int64_t device_start =
            static_cast<int64_t>(static_cast<long double>(start) * (1.0L + w.clock_drift_ppm * 1e-6L)) +
            w.clock_offset_ns;
        const bool lost =
            (w.drop_frames > 0 && FaultDraw(w.seed, serial_, k, 2) < w.drop_frames) || w.drop_slots.count(k) > 0;
        jobs_.push_back({k, start, start + w.exposure_ns, next_frame_id_++, device_start, lost});
        ++stats_.triggers;
        jobs_changed_.notify_all();
      }
    }
    if (lockstep) {
      lock.unlock();
      world->Done(device, k + ahead);
      lock.lock();
      jobs_changed_.wait(lock, [&] { return !running_ || static_cast<int>(jobs_.size()) < w.buffer_frames; });
      if (!running_) break;
    }
    slot = first_firing(k + 1, run);
  }
}

void SimCameraDevice::RenderLoop() {
  const SimCameraWorld& w = *world_;
  const std::string format = settings().pixel_format;
  while (true) {
    Job job;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      jobs_changed_.wait(lock, [&] { return !running_ || !jobs_.empty(); });
      if (!running_) return;
      job = jobs_.front();
      waiting_for_light_ = true;
    }
    auto levels = w.world->Exposure(job.t0_ns, job.t1_ns);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      waiting_for_light_ = false;
    }
    if (!levels.ok()) {
      if (absl::IsCancelled(levels.status())) return;
      Logger("sim")->warn("sim camera {}: frame {} (slot {}) lost: {}", serial_, job.frame_id, job.slot,
                          levels.status().message());
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.render_errors;
      jobs_.pop_front();
      jobs_changed_.notify_all();
      continue;
    }
    if (job.lost) {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.dropped_frames;
      jobs_.pop_front();
      jobs_changed_.notify_all();
      continue;
    }
    const RawImage raw = w.renderer->Render(*levels, (job.t1_ns - job.t0_ns) * 1e-9, job.frame_id,
                                            job.slot / std::max<int64_t>(1, w.cycle_slots));
    auto frame = std::make_shared<camera::Frame>();
    frame->frame_id = job.frame_id;
    frame->device_timestamp_ns = job.device_t0_ns;
    frame->width = static_cast<uint32_t>(raw.width);
    frame->height = static_cast<uint32_t>(raw.height);
    frame->pixel_format = format;
    frame->exposure_us = (job.t1_ns - job.t0_ns) / 1e3;
    frame->data = PackRaw(raw, format);
    sink_->OnFrame(std::move(frame));
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.frames;
    jobs_.pop_front();
    jobs_changed_.notify_all();
  }
}

camera::DeviceBacklog SimCameraDevice::Backlog() const {
  camera::DeviceBacklog b;
  if (!world_) return b;
  int64_t slot = -1;
  bool waiting = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    b.frames_owed = static_cast<int64_t>(jobs_.size());
    b.work_done = stats_.frames + stats_.dropped_frames + stats_.render_errors;
    if (!jobs_.empty()) slot = jobs_.front().slot;
    waiting = waiting_for_light_;
  }
  const CameraRenderer::Progress p = world_->renderer->progress();
  b.work_done += p.work;
  if (b.frames_owed == 0) return b;
  if (waiting) {
    b.activity = absl::StrCat("waiting for the light of slot ", slot);
  } else if (!p.activity.empty()) {
    b.activity = p.activity;
  } else {
    b.activity = absl::StrCat("rendering slot ", slot);
  }
  return b;
}

absl::Status SimCameraDevice::Trigger() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!running_)
      return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": trigger while stopped"));
    if (settings_.trigger == camera::TriggerMode::kFreeRun) {
      return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": trigger in free-run mode"));
    }
    ++pending_triggers_;
  }
  wake_.notify_all();
  return absl::OkStatus();
}

void SimCameraDevice::Run() {
  camera::CameraSettings s = settings();
  const auto period_ns = static_cast<int64_t>(std::llround(1e9 / s.frame_rate_hz));
  int64_t next_ns = clock_->NowNs();
  while (true) {
    int64_t start_ns;
    if (s.trigger == camera::TriggerMode::kFreeRun) {
      if (!clock_->SleepUntilNs(next_ns, stopping_)) return;
      std::lock_guard<std::mutex> lock(mutex_);
      if (!running_) return;
      start_ns = next_ns;
      next_ns += period_ns;
    } else {
      std::unique_lock<std::mutex> lock(mutex_);
      wake_.wait(lock, [&] { return !running_ || pending_triggers_ > 0; });
      if (!running_) return;
      --pending_triggers_;
      start_ns = clock_->NowNs();
    }
    auto frame = Expose(start_ns);
    sink_->OnFrame(std::move(frame));
  }
}

std::shared_ptr<camera::Frame> SimCameraDevice::Expose(int64_t start_ns) {
  camera::CameraSettings s = settings();
  auto frame = std::make_shared<camera::Frame>();
  frame->frame_id = next_frame_id_++;
  frame->device_timestamp_ns = start_ns;
  frame->width = s.width;
  frame->height = s.height;
  frame->pixel_format = s.pixel_format;
  frame->exposure_us = s.exposure_us;
  const int bpp = *SimBytesPerPixel(s.pixel_format);
  frame->data.resize(static_cast<size_t>(s.width) * s.height * bpp);
  // Test pattern: a diagonal ramp shifted by the frame counter, so consecutive frames differ and a stale or
  // reordered frame is visible.
  uint8_t* p = frame->data.data();
  for (uint32_t y = 0; y < s.height; ++y) {
    for (uint32_t x = 0; x < s.width; ++x) {
      uint8_t v = static_cast<uint8_t>((x + y + frame->frame_id) & 0xff);
      for (int b = 0; b < bpp; ++b) *p++ = v;
    }
  }
  return frame;
}

}  // namespace stage::sim
