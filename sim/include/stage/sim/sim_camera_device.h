// A simulated triggered camera behind the CameraDevice interface. It keeps a camera's contract (settings checked
// and read back, frames with a frame counter and a device timestamp, delivered on its own thread, triggered by
// line, software or free run).
//
// On its own its image is a test pattern. Attached to the simulated world (AttachWorld) it is the stage's camera:
// its trigger line is the world's slot clock (divided and delayed as the schedule says), each trigger opens an
// exposure, and a render thread asks the world what light the LEDs gave during that window (waiting for late light
// nodes), renders the subject under it and reads the sensor out. Frames carry the frame counter and the exposure
// start on the camera's clock (the world's, plus the clock fault's offset and drift).
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include "stage/camera/camera_device.h"
#include "stage/common/clock.h"
#include "stage/v1/rig.pb.h"

namespace stage::sim {

class WorldClient;
class CameraRenderer;

struct SimCameraWorld {
  // Not owned; must outlive the attachment.
  WorldClient* world = nullptr;
  // Renders this camera (shared: the per-pixel responses are computed once).
  std::shared_ptr<CameraRenderer> renderer;
  // Trigger plan: fires in slots k with k mod divider == phase, exposing from edge + trigger_delay for exposure_ns.
  uint32_t divider = 1;
  uint32_t phase = 0;
  int64_t trigger_delay_ns = 0;
  int64_t exposure_ns = 1'000'000;
  // Slots per cycle of patterns: the subject's pose changes from one cycle (virtual frame) to the next.
  int64_t cycle_slots = 38;
  // Real-time world: triggers that arrive while this many frames wait to be rendered are missed (the camera is busy),
  // as on a camera whose buffers are full. A lockstep world instead waits for the renderer.
  int buffer_frames = 8;
  // The camera's clock against the world's: device time = world time * (1 + drift_ppm 1e-6) + offset_ns.
  int64_t clock_offset_ns = 0;
  double clock_drift_ppm = 0;
  // Faults: fractions of triggers missed and of exposed frames lost before delivery, chosen per slot from `seed`;
  // a crash once the world passes `crash_at_ns` (world clock; < 0: never): `on_crash` runs (a node process kills
  // itself), or without one the camera falls silent.
  double miss_triggers = 0;
  double drop_frames = 0;
  // Frames exposed in these (world) slots are lost before delivery.
  std::set<int64_t> drop_slots;
  uint64_t seed = 1;
  int64_t crash_at_ns = -1;
  std::function<void()> on_crash;
};

struct SimCameraWorldStats {
  uint64_t triggers = 0;         // trigger edges that opened an exposure
  uint64_t missed_triggers = 0;  // edges the camera did not expose on (fell behind, or busy)
  uint64_t frames = 0;           // frames delivered
  uint64_t render_errors = 0;    // exposures the world could not give light for
  uint64_t dropped_frames = 0;   // exposed, then lost (a fault)
};

// Bytes per pixel of a supported PFNC pixel format (1 or 2), or nullopt if unsupported.
std::optional<int> SimBytesPerPixel(const std::string& pixel_format);

class SimCameraDevice final : public camera::CameraDevice {
 public:
  // `clock` (not owned, outlives the device) times exposures and stamps frames; `serial` names the device.
  SimCameraDevice(Clock* clock, std::string serial);
  ~SimCameraDevice() override;

  camera::CameraDescription Describe() const override;
  absl::Status Configure(const camera::CameraSettings& settings) override;
  absl::Status Start(camera::FrameSink* sink) override;
  absl::Status Stop() override;
  absl::Status Trigger() override;
  // In the world: the exposures triggered and not yet rendered, the renderer's work and what it does now.
  camera::DeviceBacklog Backlog() const override;

  // The settings in force (what a real camera would read back).
  camera::CameraSettings settings() const;

  // Takes this camera into the world (see above), from the next Start() on; only while stopped. The trigger mode must
  // be hardware (the world's trigger bus).
  absl::Status AttachWorld(SimCameraWorld world);
  SimCameraWorldStats world_stats() const;

 private:
  struct Job {
    int64_t slot;
    int64_t t0_ns, t1_ns;  // world clock
    uint64_t frame_id;
    int64_t device_t0_ns;  // the exposure start on the camera's clock
    bool lost;             // a drop fault: exposed, never delivered
  };
  // A fault injected at run time (the world hands it over with an edge); mutex_ held.
  void ApplyFault(const v1::SimFault& fault);
  void Run();
  void TriggerLoop(int device);
  void RenderLoop();
  std::shared_ptr<camera::Frame> Expose(int64_t start_ns);

  Clock* clock_;
  std::string serial_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  camera::CameraSettings settings_;  // guarded by mutex_
  bool configured_ = false;          // guarded by mutex_
  bool running_ = false;             // guarded by mutex_
  std::atomic<bool> stopping_{false};  // set by Stop() before it interrupts a free run's sleep on the clock
  uint64_t pending_triggers_ = 0;    // guarded by mutex_
  uint64_t next_frame_id_ = 0;       // acquisition thread only
  camera::FrameSink* sink_ = nullptr;
  std::thread thread_;

  std::optional<SimCameraWorld> world_;  // its fault fields change under mutex_ (trigger thread)
  int world_device_ = -1;
  std::thread render_thread_;
  std::condition_variable jobs_changed_;
  std::deque<Job> jobs_;       // guarded by mutex_
  SimCameraWorldStats stats_;  // guarded by mutex_
  // The render thread waits for the light of the front job's exposure (the world's light nodes report it).
  bool waiting_for_light_ = false;  // guarded by mutex_
};

}  // namespace stage::sim
