// The simulated stage as the rig describes it, derived once per process: the compiled schedule (what each light node
// steps through and when each camera fires), the dome, the subject and every camera's model and sensor. Light nodes,
// cameras and stage-sim's world each build the same scene from the same rig, so they agree without talking.
#pragma once

#include <atomic>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/camera_model.h"
#include "stage/common/rig.h"
#include "stage/sim/board.h"
#include "stage/sim/dome.h"
#include "stage/sim/head.h"
#include "stage/sim/light_transport.h"
#include "stage/sim/sensor_model.h"
#include "stage/sim/subject.h"
#include "stage/sim/world.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/time_base.h"
#include "stage/v1/timing.pb.h"

namespace stage::sim {

// How long the rig's "range_of_motion" performance lasts (Performance::RangeOfMotion), seconds.
inline constexpr double kRangeOfMotionS = 180;

class SimScene {
 public:
  // `rig` with defaults applied and validated; `patterns` resolved against it; files the rig names (a performance) are
  // relative to `base_dir`.
  static absl::StatusOr<std::shared_ptr<const SimScene>> Create(const v1::RigConfig& rig,
                                                                const timing::PatternSet& patterns,
                                                                const std::string& base_dir = "");
  // Loads the rig's pattern set (relative to the rig file) and creates the scene.
  static absl::StatusOr<std::shared_ptr<const SimScene>> FromLoadedRig(const LoadedRig& loaded);
  // What the subject's files lack or have that the simulator does not render (HeadModel::notes); empty otherwise.
  std::vector<std::string> notes() const { return head_ != nullptr ? head_->notes() : std::vector<std::string>(); }

  const v1::RigConfig& rig() const { return rig_; }
  const v1::Schedule& schedule() const { return schedule_; }
  const timing::TimeBase& base() const { return base_; }
  const Dome& dome() const { return dome_; }
  // The subject during virtual frame `frame` (slot / patterns per cycle): a performance holds each pose for one
  // cycle, sampled at its middle. Thread-safe; the last few poses are kept.
  std::shared_ptr<const Subject> SubjectAt(int64_t frame) const;
  // The pose of the head or board in that frame (neutral for the analytic subjects).
  HeadPose PoseAt(int64_t frame) const;
  // The performance's named sequence that frame falls in ("" when it names none).
  std::string SequenceAt(int64_t frame) const;
  // The posed model (head or board), or null for the analytic subjects; the head, or the board, or null.
  const RiggedModel* model() const { return model_.get(); }
  const HeadModel* head() const { return head_.get(); }
  const BoardModel* board() const { return board_.get(); }
  // True when the subject moves (SubjectAt differs between frames).
  bool animated() const { return model_ != nullptr && performance_.keys.size() > 1; }

  // Index in the rig, or -1.
  int CameraIndex(const std::string& id) const;
  int LightNodeIndex(const std::string& id) const;

  // The world of this rig: its rate, and each light node's rise and fall.
  WorldOptions MakeWorldOptions(bool lockstep, int64_t t0_ns) const;

  // Camera `index` at the rig's render scale, its crossed-polarizer leakage and its sensor (calibrated so that a white
  // diffuse surface facing it collects sim.full_on_electrons under the cross-polarized full-on light in its exposure).
  const CameraModel& camera(int index) const { return cameras_[static_cast<size_t>(index)]; }
  // Every camera where it really is (the rig's model moved by sim.camera_deviation), at its whole sensor: what
  // calibration should find (written to ground_truth/cameras.json).
  const CameraCalibration& true_cameras() const { return true_cameras_; }
  float leakage(int index) const { return leakages_[static_cast<size_t>(index)]; }
  const SensorParams& sensor(int index) const { return sensors_[static_cast<size_t>(index)]; }

  // Every unit's steady emitter levels under pattern `pattern` of the schedule (its rows in the light nodes' tables),
  // with light node `dark_node` (if any) dark: what an exposure inside a slot's steady light integrates.
  EmitterLevels PatternLevels(int64_t pattern, int dark_node = -1) const;
  // The patterns of the schedule whose levels light every unit of their polarization fully (the full-on ones).
  std::vector<int> FullOnPatterns() const;

  // Every sim.faults entry for `id` merged (an empty SimFault when none).
  v1::SimFault Fault(const std::string& id) const;
  // OK if `fault` could stand in sim.faults (its target is in the rig, its fields apply to it and are in range);
  // else InvalidArgument naming the field ("fault.delay_us: ...").
  absl::Status CheckFault(const v1::SimFault& fault) const;

  // A light node's switch delay after the slot edge, ns (its schedule entry).
  int64_t SwitchDelayNs(int light_node) const;

 private:
  SimScene() = default;
  absl::Status MakeSubject(const std::string& base_dir);
  v1::RigConfig rig_;
  v1::Schedule schedule_;
  timing::TimeBase base_;
  Dome dome_;
  std::shared_ptr<const Subject> still_;  // the analytic subjects, or an unmoving head
  std::shared_ptr<const RiggedModel> model_;
  std::shared_ptr<const HeadModel> head_;
  std::shared_ptr<const BoardModel> board_;
  Performance performance_;
  mutable std::mutex cache_mutex_;
  mutable std::vector<std::pair<int64_t, std::shared_ptr<const Subject>>> cache_;  // guarded by cache_mutex_
  std::vector<CameraModel> cameras_;
  CameraCalibration true_cameras_;
  std::vector<float> leakages_;
  std::vector<SensorParams> sensors_;
};

// Renders one camera's exposures: the per-pixel LED responses are computed once a pose, then each exposure is two
// matrix products (or, with ExpectOnly, a column of the pose's sums) and the sensor model. Thread-safe.
class CameraRenderer {
 public:
  CameraRenderer(std::shared_ptr<const SimScene> scene, int camera_index, int threads = 0);

  const SimScene& scene() const { return *scene_; }
  int camera_index() const { return index_; }
  // The responses in virtual frame `pose_frame` (computed when the pose changes; the latest is kept). After ExpectOnly
  // they are its exposures' sums (PixelResponses::basis): render them with RenderRadianceOf.
  std::shared_ptr<const PixelResponses> Responses(int64_t pose_frame = 0);
  // The raw sensor frame of an exposure of `exposure_s` under `levels` in virtual frame `pose_frame`; `counter` (the
  // camera's frame counter) selects the noise.
  RawImage Render(const EmitterLevels& levels, double exposure_s, uint64_t counter, int64_t pose_frame = 0);
  // Tells the renderer the only exposures it will be asked for (a take of the full-on patterns): each pose's
  // responses are then their sums under those exposures (ExposureBasis), not a row per unit. The frames are the same
  // to rounding. Should another exposure come, the renderer says so once and computes every unit's responses from then
  // on. An empty list, or one no shorter than the units (sums that would save nothing): any exposure (every unit's
  // responses, the default).
  void ExpectOnly(std::vector<EmitterLevels> levels);
  // How much memory the camera's undistorted pixel rays may keep (CameraRays; 256 MB by default): a batch render of
  // many poses at full scale keeps every sub-pixel offset's (17 of 64 MB for a 5-megapixel camera with the board's
  // 4 x 4 texture samples) rather than undistort 13 of them again for each pose.
  void KeepRays(size_t budget_bytes);

  // How far the renderer has got, from any thread: a counter of its work (rays traced, pixels lit, frames rendered)
  // and, while it precomputes a pose, what it does in words ("precomputing the subject's pose of frame 3: 45 %").
  struct Progress {
    uint64_t work = 0;
    std::string activity;
  };
  Progress progress() const;

 private:
  std::shared_ptr<const SimScene> scene_;
  int index_;
  int threads_;
  std::mutex mutex_;
  int64_t responses_frame_ = -1;                     // guarded by mutex_
  std::shared_ptr<const PixelResponses> responses_;  // guarded by mutex_
  CameraRays rays_;                                  // guarded by mutex_: undistorted once, for every pose
  std::shared_ptr<const ExposureBasis> basis_;       // guarded by mutex_; null: responses to every unit
  uint64_t stream_;
  // Progress of the pose being precomputed (-1: none), and the work of everything finished before it.
  std::atomic<int64_t> computing_frame_{-1};
  WorkProgress compute_;
  std::atomic<uint64_t> work_before_{0};
};

// `nominal` (a whole sensor) moved as `deviation` draws for camera `index` of a rig seeded `seed`.
absl::StatusOr<CameraModel> DeviatedCamera(const CameraModel& nominal, const v1::SimCameraDeviation& deviation,
                                           uint64_t seed, int index);

// Sensor bits and mosaic of a PFNC pixel format ("BayerRG8" -> 8, "RG"; "Mono12" -> 12, "mono"); InvalidArgument for
// formats the sensor model does not produce (RGB8).
absl::Status SensorFormat(const std::string& pixel_format, int* bits, std::string* mosaic);

// A raw frame as the bytes of `pixel_format` (8-bit: one byte per pixel; 12 and 16 bit: little-endian 16-bit words).
std::vector<uint8_t> PackRaw(const RawImage& raw, const std::string& pixel_format);

}  // namespace stage::sim
