// A camera as the camera node sees it. Implementations: SimCameraDevice (sim/), AravisCameraDevice
// (camera-node/src/aravis_camera_device.h). No backend library appears in this header.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"

namespace stage::camera {

enum class TriggerMode {
  // Exposes on each edge of its hardware trigger line (or, for the sim, each Trigger() call from the bus).
  kHardware,
  // Exposes on each Trigger() call; the node calls it at scheduled times.
  kSoftware,
  // Exposes continuously at frame_rate_hz once started.
  kFreeRun,
};

// What the node asks of the camera. Values are as in the rig file; the device checks them against what it can do.
struct CameraSettings {
  uint32_t width = 0;
  uint32_t height = 0;
  // GenICam PFNC name: "Mono8", "BayerRG8", ...
  std::string pixel_format = "BayerRG8";
  double frame_rate_hz = 24;
  double exposure_us = 1000;
  double gain_db = 0;
  TriggerMode trigger = TriggerMode::kHardware;
  // The sensor region's offset and the binning (both axes).
  uint32_t offset_x = 0;
  uint32_t offset_y = 0;
  uint32_t binning = 1;
  // Black level; not set: the camera's own.
  std::optional<double> black_level;
  // GigE Vision transport: packet size (bytes, IP packet), inter-packet delay (ns), PTP, packet resend, buffers in
  // the stream's pool, longest pause between reconnection attempts.
  uint32_t packet_size = 1500;
  uint32_t packet_delay_ns = 0;
  bool ptp = false;
  bool packet_resend = true;
  uint32_t buffers = 16;
  double reconnect_max_s = 5;
  std::string trigger_line = "Line0";
  bool packet_socket = true;
  // Backend features set after the standard ones, in this order (GenICam name, value as a string).
  std::vector<std::pair<std::string, std::string>> features;
};

// Transport statistics of a device since it was opened (zero where the backend has none).
struct DeviceStats {
  uint64_t frames_completed = 0;
  uint64_t frames_failed = 0;  // delivered incomplete (missing packets, timeout, size mismatch)
  uint64_t buffer_underruns = 0;
  uint64_t packets_missing = 0;
  uint64_t packets_resent = 0;
  uint64_t link_losses = 0;  // times control of the camera was lost
  uint64_t reconnects = 0;   // times it was regained and its settings restored
  bool link_up = true;
  std::string link_detail;  // why the link is down, or the last outage ("lost 12:00:01.2, back after 2.3 s")
};

// Frames a device owes: triggered (or exposed) and not delivered yet. A take waits for a camera that owes frames for as
// long as `work_done` moves, however slow the machine (docs/operators.md#when-a-take-ends).
struct DeviceBacklog {
  // Triggers accepted whose frames are neither delivered nor known lost.
  int64_t frames_owed = 0;
  // Grows while the device works on them (a simulated camera's rendering, a real one's readout); unchanged while it
  // waits for something else.
  uint64_t work_done = 0;
  // What it is doing, in words ("precomputing the subject's pose of frame 0: 45 %"); empty when idle.
  std::string activity;
};

// One delivered image. Frames are shared read-only between recorder and preview (no copies). The pixels are either
// the frame's own (`data`: the simulator) or lent from the device's buffer pool (`lent`, kept out of the pool by
// `lent_owner` until the last reference to the frame goes: zero copy from the network stack's buffer to the file).
struct Frame {
  // The camera's frame counter, from 0 at Start().
  uint64_t frame_id = 0;
  // Start of exposure on the camera's clock, ns.
  int64_t device_timestamp_ns = 0;
  uint32_t width = 0;
  uint32_t height = 0;
  std::string pixel_format;
  double exposure_us = 0;
  // Some of the frame's data never arrived (packets lost on the link): what arrived is kept, the rest is zero, and
  // `incomplete` says why ("missing packets: 3 of 1402"). Empty for a whole frame.
  std::string incomplete;
  // The first frame after the camera's link came back (control lost, reconnected, settings restored) says so
  // ("link down 12:00:01.234 for 2.31 s: ..."): the slots since the frame before are the outage's. Empty otherwise.
  std::string after_outage;
  // Row-major pixels, bytes_per_pixel * width * height bytes: the frame's own.
  std::vector<uint8_t> data;
  // Or the device's buffer, lent (see above).
  std::span<const uint8_t> lent;
  std::shared_ptr<const void> lent_owner;

  std::span<const uint8_t> pixels() const { return lent.data() != nullptr ? lent : std::span<const uint8_t>(data); }
};

// Receives frames. Called on the device's acquisition thread; must return quickly (hand off, never block on I/O).
class FrameSink {
 public:
  virtual ~FrameSink() = default;
  virtual void OnFrame(std::shared_ptr<const Frame> frame) = 0;
  // A frame came that cannot be delivered or tagged: its leader was lost on the link (GigE Vision), so it has no frame
  // id and no timestamp. It was exposed; which slot it was, the frame counter's gaps tell, except after the last
  // delivered frame, where only these calls do.
  virtual void OnFrameLost() {}
};

struct CameraDescription {
  std::string backend;  // "sim", "aravis"
  std::string vendor;
  std::string model;
  std::string serial;
};

class CameraDevice {
 public:
  virtual ~CameraDevice() = default;

  virtual CameraDescription Describe() const = 0;

  // Applies `settings` and reads them back. Only while stopped. InvalidArgument names the setting and what the camera
  // allows; FailedPrecondition if acquiring.
  virtual absl::Status Configure(const CameraSettings& settings) = 0;

  // Starts acquisition; frames go to `sink` on the device's thread until Stop() returns. `sink` must outlive Stop().
  virtual absl::Status Start(FrameSink* sink) = 0;

  // Stops acquisition; after it returns no more calls reach the sink. Idempotent.
  virtual absl::Status Stop() = 0;

  // One software trigger (TriggerMode::kSoftware). FailedPrecondition when not started or in another mode.
  virtual absl::Status Trigger() = 0;

  // Transport statistics (GetStats, `stagectl status --cameras`).
  virtual DeviceStats Stats() const { return {}; }

  // The frames it owes now (GetStats; the take's end). A device that delivers each frame within its readout time may
  // keep the default: it owes nothing the take should wait for beyond the drain.
  virtual DeviceBacklog Backlog() const { return {}; }
};

}  // namespace stage::camera
