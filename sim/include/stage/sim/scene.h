// The simulated stage as the rig describes it, derived once per process: the compiled schedule (what each light node
// steps through and when each camera fires), the dome, the subject and every camera's model and sensor. Light nodes,
// cameras and stage-sim's world each build the same scene from the same rig, so they agree without talking.
#pragma once

#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/rig.h"
#include "stage/sim/camera_model.h"
#include "stage/sim/dome.h"
#include "stage/sim/light_transport.h"
#include "stage/sim/sensor_model.h"
#include "stage/sim/subject.h"
#include "stage/sim/world.h"
#include "stage/timing/pattern_set.h"
#include "stage/timing/time_base.h"
#include "stage/v1/timing.pb.h"

namespace stage::sim {

class SimScene {
 public:
  // `rig` with defaults applied and validated; `patterns` resolved against it.
  static absl::StatusOr<std::shared_ptr<const SimScene>> Create(const v1::RigConfig& rig,
                                                                const timing::PatternSet& patterns);
  // Loads the rig's pattern set (relative to the rig file) and creates the scene.
  static absl::StatusOr<std::shared_ptr<const SimScene>> FromLoadedRig(const LoadedRig& loaded);

  const v1::RigConfig& rig() const { return rig_; }
  const v1::Schedule& schedule() const { return schedule_; }
  const timing::TimeBase& base() const { return base_; }
  const Dome& dome() const { return dome_; }
  const Subject& subject() const { return *subject_; }

  // Index in the rig, or -1.
  int CameraIndex(const std::string& id) const;
  int LightNodeIndex(const std::string& id) const;

  // The world of this rig: its rate, and each light node's rise and fall.
  WorldOptions MakeWorldOptions(bool lockstep, int64_t t0_ns) const;

  // Camera `index` at the rig's render scale, its crossed-polarizer leakage and its sensor (calibrated so that a white
  // diffuse surface facing it collects sim.full_on_electrons under the cross-polarized full-on light in its exposure).
  const CameraModel& camera(int index) const { return cameras_[static_cast<size_t>(index)]; }
  float leakage(int index) const { return leakages_[static_cast<size_t>(index)]; }
  const SensorParams& sensor(int index) const { return sensors_[static_cast<size_t>(index)]; }

  // A light node's switch delay after the slot edge, ns (its schedule entry).
  int64_t SwitchDelayNs(int light_node) const;

 private:
  SimScene() = default;
  v1::RigConfig rig_;
  v1::Schedule schedule_;
  timing::TimeBase base_;
  Dome dome_;
  std::unique_ptr<Subject> subject_;
  std::vector<CameraModel> cameras_;
  std::vector<float> leakages_;
  std::vector<SensorParams> sensors_;
};

// Renders one camera's exposures: the per-pixel LED responses are computed on first use (the subject holds still), then
// each exposure is two matrix products and the sensor model. Thread-safe.
class CameraRenderer {
 public:
  CameraRenderer(std::shared_ptr<const SimScene> scene, int camera_index, int threads = 0);

  const SimScene& scene() const { return *scene_; }
  int camera_index() const { return index_; }
  const PixelResponses& Responses();
  // The raw sensor frame of an exposure of `exposure_s` under `levels`; `frame` selects the noise.
  RawImage Render(const EmitterLevels& levels, double exposure_s, uint64_t frame);

 private:
  std::shared_ptr<const SimScene> scene_;
  int index_;
  int threads_;
  std::once_flag once_;
  PixelResponses responses_;
  uint64_t stream_;
};

// Sensor bits and mosaic of a PFNC pixel format ("BayerRG8" -> 8, "RG"; "Mono12" -> 12, "mono"); InvalidArgument for
// formats the sensor model does not produce (RGB8).
absl::Status SensorFormat(const std::string& pixel_format, int* bits, std::string* mosaic);

// A raw frame as the bytes of `pixel_format` (8-bit: one byte per pixel; 12 and 16 bit: little-endian 16-bit words).
std::vector<uint8_t> PackRaw(const RawImage& raw, const std::string& pixel_format);

}  // namespace stage::sim
