// The Aravis camera backend: see aravis_camera_device.h. The only file of the project that includes Aravis.
#include "aravis_camera_device.h"

#include <arv.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdlib>
#include <mutex>
#include <thread>
#include <utility>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "stage/common/logging.h"

namespace stage::camera {
namespace {

// A GError taken over: its message, and freed.
std::string Take(GError* error) {
  if (error == nullptr) return "";
  std::string message = error->message != nullptr ? error->message : "unknown error";
  g_error_free(error);
  return message;
}

std::string Str(const char* s) { return s != nullptr ? s : ""; }

// Numbers equal within `rel` of the first (at least `rel` absolute): a float feature rounds to its increment.
bool Near(double a, double b, double rel) { return std::abs(a - b) <= rel * std::max(1.0, std::abs(a)); }

// Two read-back values agree: equal as text, or as numbers (see Near).
bool Agrees(const std::string& asked, const std::string& got, double rel = 1e-3) {
  if (asked == got) return true;
  double a = 0, g = 0;
  if (!absl::SimpleAtod(asked, &a) || !absl::SimpleAtod(got, &g)) {
    // Booleans read back as "true"/"false" whatever was written ("1", "True").
    auto truth = [](const std::string& s) -> int {
      if (s == "true" || s == "True" || s == "1") return 1;
      if (s == "false" || s == "False" || s == "0") return 0;
      return -1;
    };
    return truth(asked) >= 0 && truth(asked) == truth(got);
  }
  return Near(a, g, rel);
}

// Adds a stream's counters since it was created to `d`.
void AddStreamCounters(ArvStream* stream, DeviceStats* d) {
  guint64 completed = 0, failures = 0, underruns = 0, resent = 0, missing = 0;
  arv_stream_get_statistics(stream, &completed, &failures, &underruns);
  if (ARV_IS_GV_STREAM(stream)) arv_gv_stream_get_statistics(ARV_GV_STREAM(stream), &resent, &missing);
  d->frames_completed += completed;
  d->frames_failed += failures;
  d->buffer_underruns += underruns;
  d->packets_resent += resent;
  d->packets_missing += missing;
}

const char* BufferStatusName(ArvBufferStatus status) {
  switch (status) {
    case ARV_BUFFER_STATUS_SUCCESS:
      return "complete";
    case ARV_BUFFER_STATUS_CLEARED:
      return "cleared";
    case ARV_BUFFER_STATUS_TIMEOUT:
      return "timeout: not all packets arrived in time";
    case ARV_BUFFER_STATUS_MISSING_PACKETS:
      return "missing packets";
    case ARV_BUFFER_STATUS_WRONG_PACKET_ID:
      return "wrong packet id";
    case ARV_BUFFER_STATUS_SIZE_MISMATCH:
      return "size mismatch: the image did not fit the buffer";
    case ARV_BUFFER_STATUS_FILLING:
      return "still filling";
    case ARV_BUFFER_STATUS_ABORTED:
      return "aborted";
    default:
      return "unknown status";
  }
}


// GigE Vision 1.x block ids are 16 bits and skip 0: unwrap them into a 64-bit count.
class BlockIdUnwrapper {
 public:
  uint64_t Next(uint64_t raw) {
    if (!last_) {
      last_ = raw;
      count_ = raw;
      return count_;
    }
    int64_t diff = static_cast<int64_t>(raw) - static_cast<int64_t>(*last_);
    if (raw <= 0xffff && *last_ <= 0xffff) {
      if (diff < -32767) diff += 65535;
      if (diff > 32767) diff -= 65535;
    }
    last_ = raw;
    count_ = static_cast<uint64_t>(static_cast<int64_t>(count_) + diff);
    return count_;
  }

 private:
  std::optional<uint64_t> last_;
  uint64_t count_ = 0;
};

}  // namespace

struct AravisCameraDevice::Impl {
  std::string camera_id;
  std::string device;
  CameraDescription description;

  mutable std::mutex mutex;  // guards everything below but the counters
  ArvCamera* camera = nullptr;
  ArvStream* stream = nullptr;
  gulong control_lost_handler = 0;
  CameraSettings settings;
  bool configured = false;
  bool running = false;  // Start()ed and not Stop()ped (across an outage)
  FrameSink* sink = nullptr;
  std::vector<std::pair<std::string, std::string>> readback;
  std::thread delivery;
  std::atomic<bool> delivering{false};
  uint64_t next_id = 0;  // the frame id the next stream's first block gets
  DeviceStats base;      // counters of earlier streams
  std::string link_detail;
  bool link_up = true;
  uint64_t link_losses = 0, reconnects = 0;

  std::thread supervisor;
  std::condition_variable wake;
  bool lost = false;      // control-lost seen, not handled yet
  bool closing = false;   // the device is being destroyed
  std::chrono::steady_clock::time_point lost_at;
  std::string outage_note;  // for the next stream's first frame (Frame::after_outage)

  std::string Who() const { return absl::StrCat("camera \"", camera_id, "\" (", device, ")"); }

  absl::Status Connect();                 // mutex held; opens `camera`
  void Disconnect();                      // mutex held
  absl::Status Apply(const CameraSettings& s, std::vector<std::pair<std::string, std::string>>* back);
  absl::Status StartStream();             // mutex held
  void StopStream();                      // mutex held
  // The delivery thread's loop: what it needs is passed in, so that it takes no lock.
  struct Delivery {
    ArvStream* stream;
    FrameSink* sink;
    uint64_t first_id;
    uint32_t width, height;
    std::string format;
    double exposure_us;
    size_t payload;  // bytes of a whole frame (what each buffer holds)
    std::string after_outage;  // for the first frame
  };
  void Deliver(Delivery d);
  void Supervise();
  absl::Status SetFeature(const std::string& name, const std::string& value,
                          std::vector<std::pair<std::string, std::string>>* back);
};

namespace {

// A buffer back into the stream's pool, its frame id and timestamp cleared: Aravis sets them from a frame's leader
// only, so a buffer whose next frame loses its leader would otherwise carry the previous frame's.
void Recycle(ArvStream* stream, ArvBuffer* buffer) {
  arv_buffer_set_frame_id(buffer, 0);
  arv_buffer_set_timestamp(buffer, 0);
  arv_stream_push_buffer(stream, buffer);
}

void OnControlLost(ArvDevice*, gpointer data) {
  auto* impl = static_cast<AravisCameraDevice::Impl*>(data);
  {
    std::lock_guard<std::mutex> lock(impl->mutex);
    impl->lost = true;
  }
  impl->wake.notify_all();
}

}  // namespace

std::vector<AravisCameraInfo> ListAravisCameras() {
  arv_update_device_list();
  std::vector<AravisCameraInfo> out;
  const unsigned n = arv_get_n_devices();
  for (unsigned i = 0; i < n; ++i) {
    out.push_back({Str(arv_get_device_id(i)), Str(arv_get_device_vendor(i)), Str(arv_get_device_model(i)),
                   Str(arv_get_device_serial_nbr(i)), Str(arv_get_device_address(i)), Str(arv_get_device_protocol(i))});
  }
  return out;
}

absl::Status AravisCameraDevice::Impl::Connect() {
  // A serial number, user id or address is matched against what discovery found; Aravis opens the rest itself
  // (its own device ids, and an IP address it can reach without discovery).
  std::string open = device;
  const std::vector<AravisCameraInfo> cameras = ListAravisCameras();
  for (const AravisCameraInfo& c : cameras) {
    if (c.serial == device || c.address == device || c.id == device) {
      open = c.id;
      break;
    }
  }
  GError* error = nullptr;
  ArvCamera* c = arv_camera_new(open.c_str(), &error);
  if (c == nullptr) {
    std::vector<std::string> found;
    for (const AravisCameraInfo& i : cameras) found.push_back(absl::StrCat(i.id, " at ", i.address));
    return absl::UnavailableError(absl::StrCat(Who(), ": cannot open it: ", Take(error), " (cameras found: ",
                                            found.empty() ? "none" : absl::StrJoin(found, ", "), ")"));
  }
  if (arv_camera_is_gv_device(c) && !arv_gv_device_is_controller(ARV_GV_DEVICE(arv_camera_get_device(c)))) {
    // Another application controls it, or its last controller's heartbeat has not timed out yet.
    g_object_unref(c);
    return absl::UnavailableError(absl::StrCat(Who(), ": opened, but another application controls it"));
  }
  camera = c;
  // Values outside a feature's bounds are refused by Aravis itself (its default writes them and lets the camera
  // clamp or ignore them).
  arv_camera_set_range_check_policy(camera, ARV_RANGE_CHECK_POLICY_ENABLE);
  control_lost_handler = g_signal_connect(arv_camera_get_device(camera), "control-lost", G_CALLBACK(OnControlLost), this);
  description.backend = "aravis";
  description.vendor = Str(arv_camera_get_vendor_name(camera, nullptr));
  description.model = Str(arv_camera_get_model_name(camera, nullptr));
  description.serial = Str(arv_camera_get_device_serial_number(camera, nullptr));
  return absl::OkStatus();
}

void AravisCameraDevice::Impl::Disconnect() {
  if (camera == nullptr) return;
  if (control_lost_handler != 0) g_signal_handler_disconnect(arv_camera_get_device(camera), control_lost_handler);
  control_lost_handler = 0;
  g_object_unref(camera);
  camera = nullptr;
}

absl::Status AravisCameraDevice::Impl::SetFeature(const std::string& name, const std::string& value,
                                                  std::vector<std::pair<std::string, std::string>>* back) {
  ArvDevice* d = arv_camera_get_device(camera);
  ArvGcNode* node = arv_device_get_feature(d, name.c_str());
  if (node == nullptr || !ARV_IS_GC_FEATURE_NODE(node)) {
    return absl::InvalidArgumentError(
        absl::StrCat(Who(), ": feature ", name, " = ", value, ": the camera has no such feature"));
  }
  auto* feature = ARV_GC_FEATURE_NODE(node);
  GError* error = nullptr;
  if (!arv_gc_feature_node_is_available(feature, &error)) {
    const std::string why = Take(error);
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": feature ", name, " = ", value,
                                                   ": not available now", why.empty() ? "" : ": " + why));
  }
  arv_gc_feature_node_set_value_from_string(feature, value.c_str(), &error);
  if (error != nullptr) {
    return absl::InvalidArgumentError(
        absl::StrCat(Who(), ": feature ", name, " = ", value, ": the camera refused it: ", Take(error)));
  }
  const std::string got = Str(arv_gc_feature_node_get_value_as_string(feature, &error));
  if (error != nullptr) {
    return absl::UnavailableError(absl::StrCat(Who(), ": feature ", name, ": cannot read it back: ", Take(error)));
  }
  if (!Agrees(value, got)) {
    return absl::InvalidArgumentError(
        absl::StrCat(Who(), ": feature ", name, " set to ", value, " reads back as ", got));
  }
  back->emplace_back(name, got);
  return absl::OkStatus();
}

absl::Status AravisCameraDevice::Impl::Apply(const CameraSettings& s,
                                             std::vector<std::pair<std::string, std::string>>* back) {
  GError* error = nullptr;
  auto failed = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": ", what, ": ", Take(error)));
  };
  auto has = [&](const char* feature) {
    return arv_camera_is_feature_available(camera, feature, nullptr) != FALSE;
  };
  // Nothing changes while the camera streams.
  arv_camera_stop_acquisition(camera, nullptr);

  // Image format control: binning and pixel format first (they change the sensor's size), then the region with its
  // offsets at 0 (they limit the width), then the offsets.
  if (arv_camera_is_binning_available(camera, nullptr)) {
    arv_camera_set_binning(camera, static_cast<int>(s.binning), static_cast<int>(s.binning), &error);
    if (error) return failed(absl::StrCat("binning ", s.binning));
    int bx = 0, by = 0;
    arv_camera_get_binning(camera, &bx, &by, nullptr);
    if (bx != static_cast<int>(s.binning) || by != static_cast<int>(s.binning)) {
      return absl::InvalidArgumentError(absl::StrCat(Who(), ": binning ", s.binning, " reads back as ", bx, "x", by));
    }
    back->emplace_back("BinningHorizontal", absl::StrCat(bx));
    back->emplace_back("BinningVertical", absl::StrCat(by));
  } else if (s.binning != 1) {
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": binning ", s.binning, ": the camera has no binning"));
  }
  if (absl::Status st = SetFeature("PixelFormat", s.pixel_format, back); !st.ok()) {
    guint n = 0;
    const char** formats = arv_camera_dup_available_pixel_formats_as_strings(camera, &n, nullptr);
    std::vector<std::string> names;
    for (guint i = 0; formats != nullptr && i < n; ++i) names.push_back(Str(formats[i]));
    g_free(formats);
    return absl::InvalidArgumentError(absl::StrCat(st.message(), " (the camera has: ", absl::StrJoin(names, ", "), ")"));
  }
  const bool offsets = arv_camera_is_region_offset_available(camera, nullptr) != FALSE;
  if (offsets) {
    std::vector<std::pair<std::string, std::string>> scratch;  // not what the camera ends up with
    for (const char* f : {"OffsetX", "OffsetY"}) {
      if (absl::Status st = SetFeature(f, "0", &scratch); !st.ok()) return st;
    }
  } else if (s.offset_x != 0 || s.offset_y != 0) {
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": offset ", s.offset_x, ", ", s.offset_y,
                                                   ": the camera has no region offsets"));
  }
  for (auto [f, v] : {std::pair{"Width", s.width}, std::pair{"Height", s.height}}) {
    if (absl::Status st = SetFeature(f, absl::StrCat(v), back); !st.ok()) {
      gint lo = 0, hi = 0;
      if (std::string(f) == "Width") {
        arv_camera_get_width_bounds(camera, &lo, &hi, nullptr);
      } else {
        arv_camera_get_height_bounds(camera, &lo, &hi, nullptr);
      }
      return absl::InvalidArgumentError(absl::StrCat(st.message(), " (the camera allows ", lo, "..", hi, ")"));
    }
  }
  if (offsets) {
    if (absl::Status st = SetFeature("OffsetX", absl::StrCat(s.offset_x), back); !st.ok()) return st;
    if (absl::Status st = SetFeature("OffsetY", absl::StrCat(s.offset_y), back); !st.ok()) return st;
  }

  // Acquisition control: continuous, the exposure, the trigger.
  arv_camera_set_acquisition_mode(camera, ARV_ACQUISITION_MODE_CONTINUOUS, &error);
  if (error) return failed("AcquisitionMode = Continuous");
  back->emplace_back("AcquisitionMode", "Continuous");
  if (arv_camera_is_exposure_auto_available(camera, nullptr)) {
    arv_camera_set_exposure_time_auto(camera, ARV_AUTO_OFF, &error);
    if (error) return failed("ExposureAuto = Off");
  }
  arv_camera_set_exposure_time(camera, s.exposure_us, &error);
  if (error) {
    double lo = 0, hi = 0;
    arv_camera_get_exposure_time_bounds(camera, &lo, &hi, nullptr);
    return failed(absl::StrFormat("exposure %g us (the camera allows %g..%g us)", s.exposure_us, lo, hi));
  }
  const double exposure = arv_camera_get_exposure_time(camera, nullptr);
  if (!Near(s.exposure_us, exposure, 0.01)) {
    return absl::InvalidArgumentError(
        absl::StrFormat("%s: exposure %g us reads back as %g us", Who(), s.exposure_us, exposure));
  }
  back->emplace_back("ExposureTime", absl::StrCat(exposure));
  switch (s.trigger) {
    case TriggerMode::kHardware:
    case TriggerMode::kSoftware: {
      const char* source = s.trigger == TriggerMode::kHardware ? s.trigger_line.c_str() : "Software";
      // FrameStart, on, this source (rising edge where the camera has an activation).
      arv_camera_set_trigger(camera, source, &error);
      if (error) return failed(absl::StrCat("trigger ", source));
      const std::string got = Str(arv_camera_get_trigger_source(camera, nullptr));
      if (got != source) {
        return absl::InvalidArgumentError(absl::StrCat(Who(), ": TriggerSource ", source, " reads back as ", got));
      }
      back->emplace_back("TriggerSelector", "FrameStart");
      back->emplace_back("TriggerMode", "On");
      back->emplace_back("TriggerSource", got);
      break;
    }
    case TriggerMode::kFreeRun:
      arv_camera_clear_triggers(camera, &error);
      if (error) return failed("TriggerMode = Off");
      back->emplace_back("TriggerMode", "Off");
      if (arv_camera_is_frame_rate_available(camera, nullptr)) {
        arv_camera_set_frame_rate(camera, s.frame_rate_hz, &error);
        if (error) return failed(absl::StrFormat("frame rate %g fps", s.frame_rate_hz));
        back->emplace_back("AcquisitionFrameRate", absl::StrCat(arv_camera_get_frame_rate(camera, nullptr)));
      }
      break;
  }

  // Analog control.
  if (arv_camera_is_gain_auto_available(camera, nullptr)) {
    arv_camera_set_gain_auto(camera, ARV_AUTO_OFF, &error);
    if (error) return failed("GainAuto = Off");
  }
  if (arv_camera_is_gain_available(camera, nullptr)) {
    arv_camera_set_gain(camera, s.gain_db, &error);
    if (error) return failed(absl::StrFormat("gain %g", s.gain_db));
    back->emplace_back("Gain", absl::StrCat(arv_camera_get_gain(camera, nullptr)));
  } else if (s.gain_db != 0) {
    return absl::InvalidArgumentError(absl::StrFormat("%s: gain %g dB: the camera has no gain", Who(), s.gain_db));
  }
  if (s.black_level) {
    if (!arv_camera_is_black_level_available(camera, nullptr)) {
      return absl::InvalidArgumentError(
          absl::StrFormat("%s: black level %g: the camera has no BlackLevel", Who(), *s.black_level));
    }
    arv_camera_set_black_level(camera, *s.black_level, &error);
    if (error) return failed(absl::StrFormat("black level %g", *s.black_level));
    back->emplace_back("BlackLevel", absl::StrCat(arv_camera_get_black_level(camera, nullptr)));
  }

  // Transport layer (GigE Vision).
  if (arv_camera_is_gv_device(camera)) {
    arv_camera_gv_set_packet_size(camera, static_cast<int>(s.packet_size), &error);
    if (error) return failed(absl::StrCat("packet size ", s.packet_size));
    const guint packet = arv_camera_gv_get_packet_size(camera, nullptr);
    if (packet != s.packet_size) {
      return absl::InvalidArgumentError(
          absl::StrCat(Who(), ": GevSCPSPacketSize ", s.packet_size, " reads back as ", packet));
    }
    back->emplace_back("GevSCPSPacketSize", absl::StrCat(packet));
    if (has("GevSCPD")) {
      arv_camera_gv_set_packet_delay(camera, s.packet_delay_ns, &error);
      if (error) return failed(absl::StrCat("packet delay ", s.packet_delay_ns, " ns"));
      back->emplace_back("GevSCPD", absl::StrCat(arv_camera_gv_get_packet_delay(camera, nullptr)));
    } else if (s.packet_delay_ns != 0) {
      return absl::InvalidArgumentError(
          absl::StrCat(Who(), ": packet delay ", s.packet_delay_ns, " ns: the camera has no GevSCPD"));
    }
  }
  if (s.ptp) {
    const char* ptp = has("PtpEnable") ? "PtpEnable" : has("GevIEEE1588") ? "GevIEEE1588" : nullptr;
    if (ptp == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(Who(), ": ptp: the camera has neither PtpEnable nor GevIEEE1588"));
    }
    if (absl::Status st = SetFeature(ptp, "true", back); !st.ok()) return st;
  }

  // The rig's own features, last, in order.
  for (const auto& [name, value] : s.features) {
    if (absl::Status st = SetFeature(name, value, back); !st.ok()) return st;
  }
  return absl::OkStatus();
}

absl::Status AravisCameraDevice::Impl::StartStream() {
  GError* error = nullptr;
  const guint payload = arv_camera_get_payload(camera, &error);
  if (error) return absl::UnavailableError(absl::StrCat(Who(), ": cannot read its payload size: ", Take(error)));
  if (arv_camera_is_gv_device(camera)) {
    arv_camera_gv_set_stream_options(
        camera, settings.packet_socket ? ARV_GV_STREAM_OPTION_NONE : ARV_GV_STREAM_OPTION_PACKET_SOCKET_DISABLED);
  }
  ArvStream* s = arv_camera_create_stream(camera, nullptr, nullptr, &error);
  if (s == nullptr) return absl::UnavailableError(absl::StrCat(Who(), ": cannot open its stream: ", Take(error)));
  if (ARV_IS_GV_STREAM(s)) {
    // A receive buffer of four frames (the kernel caps it at net.core.rmem_max): its default drops most of a frame
    // sent in one burst. Resend only where the camera can (Aravis turns it off for a camera that says it cannot).
    g_object_set(s, "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_FIXED, "socket-buffer-size",
                 static_cast<gint>(std::clamp<guint64>(4ull * payload, 4u << 20, 64u << 20)), nullptr);
    if (!settings.packet_resend) g_object_set(s, "packet-resend", ARV_GV_STREAM_PACKET_RESEND_NEVER, nullptr);
  }
  for (uint32_t i = 0; i < settings.buffers; ++i) arv_stream_push_buffer(s, arv_buffer_new_allocate(payload));
  stream = s;
  int width = 0, height = 0, x = 0, y = 0;
  arv_camera_get_region(camera, &x, &y, &width, &height, nullptr);
  delivering = true;
  g_object_ref(s);  // the delivery thread's
  delivery = std::thread([this, d = Delivery{s, sink, next_id, static_cast<uint32_t>(width),
                                             static_cast<uint32_t>(height), settings.pixel_format,
                                             settings.exposure_us, payload, std::exchange(outage_note, {})}] {
    Deliver(d);
  });
  arv_camera_start_acquisition(camera, &error);
  if (error) {
    const std::string why = Take(error);
    StopStream();
    return absl::UnavailableError(absl::StrCat(Who(), ": cannot start acquisition: ", why));
  }
  return absl::OkStatus();
}

void AravisCameraDevice::Impl::StopStream() {
  if (stream == nullptr) return;
  if (camera != nullptr) arv_camera_stop_acquisition(camera, nullptr);
  delivering = false;
  // The delivery thread takes no lock: joining it with the mutex held is safe.
  if (delivery.joinable()) delivery.join();
  AddStreamCounters(stream, &base);
  // Frames still held by the recorder keep the stream (and its buffers) alive until they are released.
  g_object_unref(stream);
  stream = nullptr;
}

void AravisCameraDevice::Impl::Deliver(Delivery d) {
  ArvStream* s = d.stream;
  BlockIdUnwrapper unwrap;
  std::optional<uint64_t> first_block;
  // Frames that came without their leader before the first with one: exposed, so counted (the ids count from the first
  // frame the stream brings, and the first one with an id is not that one).
  uint64_t leaderless_first = 0;
  while (true) {
    // Once stopped, what the stream has already closed is still delivered: nothing it counted is left behind.
    const bool running_now = delivering.load();
    ArvBuffer* buffer = running_now ? arv_stream_timeout_pop_buffer(s, 100'000) : arv_stream_try_pop_buffer(s);
    if (buffer == nullptr) {
      if (running_now) continue;
      break;
    }
    const ArvBufferStatus status = arv_buffer_get_status(buffer);
    if (arv_buffer_get_frame_id(buffer) == 0) {
      // The leader was lost: no frame id, no timestamp, nothing to tag the frame by (Aravis sets both from the
      // leader only, which is why every buffer goes back to the pool with them cleared). The stream counts it as a
      // failure and the frame counter's gap marks its slot as exposed and not delivered; the sink is told, for a gap
      // the counter cannot show (after the take's last delivered frame).
      Recycle(s, buffer);
      if (!first_block) ++leaderless_first;
      if (d.sink != nullptr) d.sink->OnFrameLost();
      continue;
    }
    auto frame = std::make_shared<Frame>();
    const uint64_t block = unwrap.Next(arv_buffer_get_frame_id(buffer));
    if (!first_block) first_block = block;
    frame->frame_id = d.first_id + leaderless_first + (block - *first_block);
    next_id = frame->frame_id + 1;  // only this thread writes it while the stream runs
    frame->device_timestamp_ns = static_cast<int64_t>(arv_buffer_get_timestamp(buffer));
    size_t size = 0;
    const void* data = nullptr;
    if (status == ARV_BUFFER_STATUS_SUCCESS) {
      data = arv_buffer_get_image_data(buffer, &size);
      frame->width = static_cast<uint32_t>(arv_buffer_get_image_width(buffer));
      frame->height = static_cast<uint32_t>(arv_buffer_get_image_height(buffer));
      frame->pixel_format = d.format;
    } else {
      // What arrived, in place, the rest zero: the whole buffer (Aravis reports no size for a failed one).
      data = arv_buffer_get_data(buffer, nullptr);
      size = d.payload;
      frame->width = d.width;
      frame->height = d.height;
      frame->pixel_format = d.format;
      frame->incomplete = BufferStatusName(status);
    }
    frame->exposure_us = d.exposure_us;
    frame->after_outage = std::exchange(d.after_outage, std::string());
    frame->lent = std::span<const uint8_t>(static_cast<const uint8_t*>(data), size);
    g_object_ref(s);
    frame->lent_owner = std::shared_ptr<const void>(buffer, [s](const void* b) {
      Recycle(s, static_cast<ArvBuffer*>(const_cast<void*>(b)));
      g_object_unref(s);
    });
    if (d.sink != nullptr) d.sink->OnFrame(std::move(frame));
  }
  g_object_unref(s);
}

void AravisCameraDevice::Impl::Supervise() {
  auto log = Logger("camera.aravis");
  std::unique_lock<std::mutex> lock(mutex);
  while (true) {
    wake.wait(lock, [&] { return lost || closing; });
    if (closing) return;
    lost = false;
    if (!link_up) continue;  // already reconnecting
    link_up = false;
    ++link_losses;
    lost_at = std::chrono::steady_clock::now();
    const absl::Time lost_wall = absl::Now();
    link_detail = "control of the camera lost; reconnecting";
    log->error("{}: control lost; reconnecting", Who());
    StopStream();
    Disconnect();
    double backoff = 0.05;
    while (!closing) {
      wake.wait_for(lock, std::chrono::duration<double>(backoff), [&] { return closing; });
      if (closing) return;
      absl::Status s = Connect();
      std::vector<std::pair<std::string, std::string>> back;
      outage_note = absl::StrFormat(
          "link down %s for %.2f s (control of the camera lost; reconnected, settings restored)",
          absl::FormatTime("%H:%M:%E3S", lost_wall, absl::LocalTimeZone()),
          std::chrono::duration<double>(std::chrono::steady_clock::now() - lost_at).count());
      if (s.ok() && configured) s = Apply(settings, &back);
      if (s.ok() && running) s = StartStream();
      if (s.ok()) {
        const double out_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - lost_at).count();
        link_up = true;
        lost = false;  // a control-lost of the old connection, if any came late
        ++reconnects;
        link_detail = absl::StrFormat("reconnected after %.2f s, settings restored", out_s);
        log->warn("{}: {}", Who(), link_detail);
        readback = std::move(back);
        if (!running) outage_note.clear();  // no take's frames in between to tell
        break;
      }
      StopStream();
      Disconnect();
      link_detail = absl::StrCat("control of the camera lost; reconnecting: ", s.message());
      backoff = std::min(settings.reconnect_max_s, backoff * 2);
    }
  }
}

AravisCameraDevice::AravisCameraDevice(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

absl::StatusOr<std::unique_ptr<AravisCameraDevice>> AravisCameraDevice::Open(const std::string& camera_id,
                                                                             const std::string& device) {
  auto impl = std::make_unique<Impl>();
  impl->camera_id = camera_id;
  impl->device = device;
  {
    std::lock_guard<std::mutex> lock(impl->mutex);
    if (absl::Status s = impl->Connect(); !s.ok()) return s;
  }
  Impl* raw = impl.get();
  impl->supervisor = std::thread([raw] { raw->Supervise(); });
  return std::unique_ptr<AravisCameraDevice>(new AravisCameraDevice(std::move(impl)));
}

AravisCameraDevice::~AravisCameraDevice() {
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    impl_->closing = true;
    impl_->running = false;
    impl_->StopStream();
  }
  impl_->wake.notify_all();
  if (impl_->supervisor.joinable()) impl_->supervisor.join();
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->Disconnect();
}

CameraDescription AravisCameraDevice::Describe() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->description;
}

absl::Status AravisCameraDevice::Configure(const CameraSettings& settings) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  if (impl_->running) return absl::FailedPreconditionError(absl::StrCat(impl_->Who(), ": configure while acquiring"));
  if (impl_->camera == nullptr) {
    return absl::UnavailableError(absl::StrCat(impl_->Who(), ": ", impl_->link_detail));
  }
  std::vector<std::pair<std::string, std::string>> back;
  absl::Status s = impl_->Apply(settings, &back);
  if (!s.ok()) return s;
  impl_->settings = settings;
  impl_->configured = true;
  impl_->readback = std::move(back);
  return absl::OkStatus();
}

absl::Status AravisCameraDevice::Start(FrameSink* sink) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  if (!impl_->configured) return absl::FailedPreconditionError(absl::StrCat(impl_->Who(), ": start before configure"));
  if (impl_->running) return absl::OkStatus();
  impl_->sink = sink;
  impl_->running = true;
  if (impl_->camera == nullptr) return absl::OkStatus();  // reconnecting: the stream starts when the camera is back
  absl::Status s = impl_->StartStream();
  if (!s.ok()) impl_->running = false;
  return s;
}

absl::Status AravisCameraDevice::Stop() {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->running = false;
  impl_->StopStream();
  impl_->sink = nullptr;
  return absl::OkStatus();
}

absl::Status AravisCameraDevice::Trigger() {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  if (!impl_->running || impl_->settings.trigger != TriggerMode::kSoftware) {
    return absl::FailedPreconditionError(absl::StrCat(impl_->Who(), ": a software trigger needs the camera started "
                                                                    "with trigger source scheduled-software"));
  }
  if (impl_->camera == nullptr) return absl::UnavailableError(absl::StrCat(impl_->Who(), ": ", impl_->link_detail));
  GError* error = nullptr;
  arv_camera_software_trigger(impl_->camera, &error);
  if (error) return absl::UnavailableError(absl::StrCat(impl_->Who(), ": software trigger: ", Take(error)));
  return absl::OkStatus();
}

DeviceStats AravisCameraDevice::Stats() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  DeviceStats d = impl_->base;
  if (impl_->stream != nullptr) AddStreamCounters(impl_->stream, &d);
  d.link_losses = impl_->link_losses;
  d.reconnects = impl_->reconnects;
  d.link_up = impl_->link_up;
  d.link_detail = impl_->link_detail;
  return d;
}

std::vector<std::pair<std::string, std::string>> AravisCameraDevice::ReadBack() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->readback;
}

}  // namespace stage::camera
