// Fake GigE Vision cameras rendering the simulated stage: see gige_fake_camera.h.
#include "stage/sim/gige_fake_camera.h"

extern "C" {
#include <arv.h>
}
#include <arpa/inet.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <span>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/clock.h"
#include "stage/common/logging.h"
#include "stage/common/rig.h"
#include "stage/common/status.h"
#include "stage/sim/sim_camera_device.h"
#include "stage/sim/world_devices.h"

namespace stage::sim {
namespace {

// The fake's own trigger logic fires only with its TriggerSource register (0x304) at Software. The fake served here
// keeps that register at Software for itself and moves the TriggerSource feature the node sees to a free register, so
// that Line0 (the stage's hardware trigger) is a setting the node can make and read back, and the simulator pulls
// the line by setting the TriggerSoftware register when the world's trigger edge comes.
constexpr uint32_t kInternalTriggerSource = 0x304;  // ARV_FAKE_CAMERA_REGISTER_TRIGGER_SOURCE
constexpr uint32_t kVisibleTriggerSource = 0x314;   // unused by the fake (0x300..0x30c: FrameStart's trigger)
constexpr uint32_t kLine0 = 0;                      // the fake's TriggerSource enumeration: Line0 0, Software 1

absl::StatusOr<std::string> PatchedGenicam() {
  ArvFakeCamera* probe = arv_fake_camera_new("probe");
  size_t size = 0;
  const char* xml = arv_fake_camera_get_genicam_xml(probe, &size);
  std::string text = xml != nullptr ? std::string(xml, size) : std::string();
  g_object_unref(probe);
  const size_t reg = text.find("<IntReg Name=\"TriggerSourceRegister\"");
  const std::string from = absl::StrFormat("<Address>0x%x</Address>", kInternalTriggerSource);
  const size_t at = reg == std::string::npos ? std::string::npos : text.find(from, reg);
  if (at == std::string::npos || text.find("</IntReg>", reg) < at) {
    return absl::InternalError(
        "Aravis's fake camera description has no TriggerSourceRegister at 0x304 (another Aravis version?): the "
        "simulated hardware trigger cannot be wired");
  }
  text.replace(at, from.size(), absl::StrFormat("<Address>0x%x</Address>", kVisibleTriggerSource));
  return text;
}

uint32_t Register(ArvFakeCamera* fake, uint32_t address) {
  guint32 value = 0;
  arv_fake_camera_read_register(fake, address, &value);
  return value;
}

}  // namespace

absl::Status GigEFakeOptions::Validate() const {
  in_addr a{};
  if (inet_pton(AF_INET, address.c_str(), &a) != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("fake GigE camera ", camera_id, ": \"", address, "\" is not an IPv4 address"));
  }
  if (!(packet_loss >= 0 && packet_loss <= 1)) {
    return absl::InvalidArgumentError(
        absl::StrFormat("fake GigE camera %s: packet loss %g is not in [0, 1]", camera_id, packet_loss));
  }
  if (!(trigger_poll_hz >= 1 && trigger_poll_hz <= 10000)) {
    return absl::InvalidArgumentError(
        absl::StrFormat("fake GigE camera %s: trigger poll %g Hz is not in [1, 10000]", camera_id, trigger_poll_hz));
  }
  if (!(link_down_s >= 0)) {
    return absl::InvalidArgumentError(absl::StrFormat("fake GigE camera %s: link down for %g s", camera_id, link_down_s));
  }
  return absl::OkStatus();
}

absl::StatusOr<GigEFakeOptions> GigEFakeOptionsFromRig(const SimScene& scene, const std::string& camera_id) {
  const v1::CameraConfig* config = nullptr;
  for (const auto& c : scene.rig().cameras()) {
    if (c.id() == camera_id) config = &c;
  }
  if (config == nullptr) return absl::NotFoundError(absl::StrCat("no camera \"", camera_id, "\" in the rig"));
  GigEFakeOptions o;
  o.camera_id = camera_id;
  o.address = config->device();
  // Several polls per frame: a frame waits at most a fraction of its period to be sent.
  o.trigger_poll_hz = std::clamp(config->frame_rate_hz() * 4, 100.0, 1000.0);
  for (const auto& f : scene.rig().sim().faults()) {
    if (f.target() != camera_id) continue;
    if (f.has_packet_loss()) o.packet_loss = f.packet_loss();
    if (f.has_link_down_at_s()) {
      o.link_down_at_s = f.link_down_at_s();
      o.link_down_s = f.link_down_s();
    }
  }
  STAGE_RETURN_IF_ERROR(o.Validate());
  return o;
}

struct GigEFakeCamera::Impl final : camera::FrameSink {
  GigEFakeOptions options;
  std::shared_ptr<const SimScene> scene;
  WorldClient* world = nullptr;
  v1::CameraConfig config;
  std::string genicam_path;
  RealClock clock{RealClock::Kind::kRealtime};
  std::unique_ptr<SimCameraDevice> sensor;

  mutable std::mutex mutex;
  ArvGvFakeCamera* gv = nullptr;  // null while off the network
  std::deque<std::shared_ptr<const camera::Frame>> pending;  // rendered, triggered, not sent yet
  GigEFakeStats stats;
  bool outage_started = false;
  bool stopping = false;
  std::condition_variable stop_cv;
  std::thread outage;

  ~Impl() override {
    if (sensor) (void)sensor->Stop();  // no more frames from the world
    {
      std::lock_guard<std::mutex> lock(mutex);
      stopping = true;
    }
    stop_cv.notify_all();
    if (outage.joinable()) outage.join();
    ArvGvFakeCamera* last = nullptr;
    {
      std::lock_guard<std::mutex> lock(mutex);
      std::swap(last, gv);
    }
    if (last != nullptr) g_object_unref(last);  // joins the fake's thread (which may be in Fill: not under `mutex`)
    if (!genicam_path.empty()) std::remove(genicam_path.c_str());
  }

  // A fresh fake at the address, as a camera just powered on.
  absl::StatusOr<ArvGvFakeCamera*> PowerOn() {
    ArvGvFakeCamera* fake =
        arv_gv_fake_camera_new_full(options.address.c_str(), options.camera_id.c_str(), genicam_path.c_str());
    if (fake == nullptr || !arv_gv_fake_camera_is_running(fake)) {
      if (fake != nullptr) g_object_unref(fake);
      return absl::UnavailableError(absl::StrCat(
          "fake GigE camera ", options.camera_id, ": cannot listen at ", options.address,
          ": the address must be on an interface of this machine (as root: ip addr add ", options.address,
          "/8 dev lo), and no other camera may listen there"));
    }
    ArvFakeCamera* camera = arv_gv_fake_camera_get_fake_camera(fake);
    // The sensor is the rig's; the sim may render it smaller (sim.render_scale): frames are scaled up to fit.
    arv_fake_camera_write_register(camera, ARV_FAKE_CAMERA_REGISTER_SENSOR_WIDTH, config.width());
    arv_fake_camera_write_register(camera, ARV_FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, config.height());
    arv_fake_camera_write_register(camera, ARV_FAKE_CAMERA_REGISTER_WIDTH, config.width());
    arv_fake_camera_write_register(camera, ARV_FAKE_CAMERA_REGISTER_HEIGHT, config.height());
    arv_fake_camera_write_register(camera, kInternalTriggerSource, 1);
    arv_fake_camera_write_register(camera, kVisibleTriggerSource, kLine0);
    arv_fake_camera_set_trigger_frequency(camera, options.trigger_poll_hz);
    arv_fake_camera_set_fill_pattern(camera, &Impl::Fill, this);
    g_object_set(fake, "gvsp-lost-ratio", options.packet_loss, nullptr);
    return fake;
  }

  // FrameSink: a frame the world rendered at one of the camera's trigger edges.
  void OnFrame(std::shared_ptr<const camera::Frame> frame) override {
    std::unique_lock<std::mutex> lock(mutex);
    ++stats.rendered;
    const double world_s = static_cast<double>(frame->device_timestamp_ns - world->t0_ns()) * 1e-9;
    if (options.link_down_at_s >= 0 && !outage_started && world_s >= options.link_down_at_s) {
      outage_started = true;
      outage = std::thread([this] { Outage(); });
    }
    if (gv == nullptr) {
      ++stats.link_down;
      return;
    }
    ArvFakeCamera* camera = arv_gv_fake_camera_get_fake_camera(gv);
    const bool acquiring = arv_fake_camera_get_control_channel_privilege(camera) != 0 &&
                           arv_fake_camera_get_acquisition_status(camera) != 0;
    const bool on_line = Register(camera, ARV_FAKE_CAMERA_REGISTER_TRIGGER_MODE) == 1 &&
                         Register(camera, kVisibleTriggerSource) == kLine0;
    if (!acquiring || !on_line) {
      ++stats.not_acquiring;
      return;
    }
    if (pending.size() >= 64) {
      Logger("sim.gige")->warn("{}: 64 frames wait to be sent; dropping the oldest", options.camera_id);
      pending.pop_front();
    }
    pending.push_back(std::move(frame));
    arv_fake_camera_write_register(camera, ARV_FAKE_CAMERA_REGISTER_TRIGGER_SOFTWARE, 1);  // the trigger line
  }

  void Outage() {
    ArvGvFakeCamera* fake = nullptr;
    {
      std::lock_guard<std::mutex> lock(mutex);
      std::swap(fake, gv);
      pending.clear();
      ++stats.outages;
    }
    Logger("sim.gige")
        ->warn("{}: off the network for {} s (sim.faults link_down)", options.camera_id, options.link_down_s);
    if (fake != nullptr) g_object_unref(fake);
    std::unique_lock<std::mutex> lock(mutex);
    if (stop_cv.wait_for(lock, std::chrono::duration<double>(options.link_down_s), [&] { return stopping; })) return;
    lock.unlock();
    auto back = PowerOn();
    lock.lock();
    if (!back.ok()) {
      Logger("sim.gige")->error("{}: cannot come back: {}", options.camera_id, back.status().message());
      return;
    }
    gv = *back;
    Logger("sim.gige")->info("{}: back on the network at {}", options.camera_id, options.address);
  }

  // Aravis's fill callback, on the fake's thread, for each frame it sends: the oldest triggered rendering, scaled to the
  // fake's image (a Bayer mosaic keeps its 2x2 cells), stamped with its exposure start.
  static void Fill(ArvBuffer* buffer, void* data, guint32 /*exposure_us*/, guint32 /*gain*/, ArvPixelFormat format) {
    auto* self = static_cast<Impl*>(data);
    std::shared_ptr<const camera::Frame> frame;
    {
      std::lock_guard<std::mutex> lock(self->mutex);
      if (!self->pending.empty()) {
        frame = std::move(self->pending.front());
        self->pending.pop_front();
        ++self->stats.sent;
        if (!self->pending.empty() && self->gv != nullptr) {
          arv_fake_camera_write_register(arv_gv_fake_camera_get_fake_camera(self->gv),
                                         ARV_FAKE_CAMERA_REGISTER_TRIGGER_SOFTWARE, 1);  // the next one
        }
      }
    }
    const auto width = static_cast<size_t>(arv_buffer_get_image_width(buffer));
    const auto height = static_cast<size_t>(arv_buffer_get_image_height(buffer));
    const size_t bpp = std::max<size_t>(1, ARV_PIXEL_FORMAT_BIT_PER_PIXEL(format) / 8);
    size_t size = 0;
    auto* out = static_cast<uint8_t*>(const_cast<void*>(arv_buffer_get_data(buffer, &size)));
    // The fake allocates width x height bytes whatever the format (Aravis 0.8); inside the callback the buffer reports
    // no size yet.
    const size_t capacity = width * height;
    if (out == nullptr) return;
    if (frame == nullptr) {
      // Triggered by software or running free: no picture from the world.
      std::fill(out, out + capacity, 0);
      arv_buffer_set_timestamp(buffer, static_cast<guint64>(g_get_real_time()) * 1000);
      return;
    }
    arv_buffer_set_timestamp(buffer, static_cast<guint64>(frame->device_timestamp_ns));
    const std::span<const uint8_t> in = frame->pixels();
    const size_t fw = frame->width, fh = frame->height;
    const size_t fbpp = fw * fh > 0 ? in.size() / (fw * fh) : 0;
    if (fbpp != bpp || fw == 0 || fh == 0 || width == 0 || height == 0) {
      std::fill(out, out + capacity, 0);
      return;
    }
    const size_t rows = std::min(height, capacity / (width * bpp));
    // Source column of each output column, by 2x2 cells (parity kept: Bayer colours stay where they were).
    auto map = [](size_t x, size_t out_n, size_t in_n) {
      if (out_n < 2 || in_n < 2) return std::min(x * in_n / std::max<size_t>(out_n, 1), in_n - 1);
      const size_t cell = (x / 2) * (in_n / 2) / (out_n / 2);
      return std::min(cell * 2 + x % 2, in_n - 1);
    };
    std::vector<size_t> cols(width);
    for (size_t x = 0; x < width; ++x) cols[x] = map(x, width, fw) * bpp;
    for (size_t y = 0; y < rows; ++y) {
      const uint8_t* src = in.data() + map(y, height, fh) * fw * bpp;
      uint8_t* dst = out + y * width * bpp;
      for (size_t x = 0; x < width; ++x) std::memcpy(dst + x * bpp, src + cols[x], bpp);
    }
  }
};

GigEFakeCamera::GigEFakeCamera(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

GigEFakeCamera::~GigEFakeCamera() = default;

const GigEFakeOptions& GigEFakeCamera::options() const { return impl_->options; }

GigEFakeStats GigEFakeCamera::stats() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->stats;
}

absl::StatusOr<std::unique_ptr<GigEFakeCamera>> GigEFakeCamera::Create(std::shared_ptr<const SimScene> scene,
                                                                       WorldClient* world, GigEFakeOptions options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  auto impl = std::make_unique<Impl>();
  impl->options = std::move(options);
  impl->scene = scene;
  impl->world = world;
  const std::string& id = impl->options.camera_id;
  bool found = false;
  for (const auto& c : scene->rig().cameras()) {
    if (c.id() == id) {
      impl->config = c;
      found = true;
    }
  }
  if (!found) return absl::NotFoundError(absl::StrCat("fake GigE camera: no camera \"", id, "\" in the rig"));

  STAGE_ASSIGN_OR_RETURN(std::string xml, PatchedGenicam());
  std::string path = (std::filesystem::temp_directory_path() / "fastage-gige-XXXXXX.xml").string();
  const int fd = mkstemps(path.data(), 4);
  if (fd < 0) return absl::UnavailableError(absl::StrCat(path, ": cannot create the fake camera's description"));
  close(fd);
  impl->genicam_path = path;
  {
    std::ofstream out(path, std::ios::binary);
    out << xml;
    if (!out) return absl::UnavailableError(absl::StrCat(path, ": cannot write the fake camera's description"));
  }

  // The sensor: the camera in the world, triggered by its line on the world's bus.
  impl->sensor = std::make_unique<SimCameraDevice>(&impl->clock, id);
  camera::CameraSettings s;
  s.width = impl->config.width();
  s.height = impl->config.height();
  s.pixel_format = PixelFormatName(impl->config.pixel_format());
  s.frame_rate_hz = impl->config.frame_rate_hz();
  s.exposure_us = impl->config.exposure_us();
  s.gain_db = impl->config.gain_db();
  s.trigger = camera::TriggerMode::kHardware;
  STAGE_RETURN_IF_ERROR(Annotate(impl->sensor->Configure(s), absl::StrCat("fake GigE camera ", id)));
  STAGE_ASSIGN_OR_RETURN(SimCameraWorld plan, CameraWorld(scene, id, world));
  STAGE_RETURN_IF_ERROR(impl->sensor->AttachWorld(std::move(plan)));

  STAGE_ASSIGN_OR_RETURN(impl->gv, impl->PowerOn());
  STAGE_RETURN_IF_ERROR(impl->sensor->Start(impl.get()));
  Logger("sim.gige")
      ->info("{}: fake GigE Vision camera at {} ({}x{} {}, packet loss {})", id, impl->options.address,
             impl->config.width(), impl->config.height(), s.pixel_format, impl->options.packet_loss);
  return std::unique_ptr<GigEFakeCamera>(new GigEFakeCamera(std::move(impl)));
}

}  // namespace stage::sim
