// Simulated camera device.
#include "stage/sim/sim_camera_device.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/string_view.h"

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

absl::Status SimCameraDevice::Start(camera::FrameSink* sink) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!configured_)
    return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": start before configure"));
  if (running_) return absl::FailedPreconditionError(absl::StrCat("sim camera ", serial_, ": already acquiring"));
  sink_ = sink;
  running_ = true;
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
  clock_->Interrupt();  // a free-running acquisition sleeps on the clock
  if (thread_.joinable()) thread_.join();
  sink_ = nullptr;
  return absl::OkStatus();
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
      bool reached = clock_->SleepUntilNs(next_ns);
      std::lock_guard<std::mutex> lock(mutex_);
      if (!running_) return;
      if (!reached) continue;
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
