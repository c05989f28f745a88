// Cameras for photometric processing: see calibration.h.
#include "stage/processing/calibration.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace stage::processing {
namespace {

// The simulator's sensor (sim/src/scene.cc, SensorParams): 8-bit formats are 8-bit, the others carry 12 bits; the
// full well spans the levels above black; gain in dB takes electrons per DN down. Checked against the simulator by
// stage_processing_sim_test.
struct SimSensor {
  double white_dn, electrons_per_dn, read_noise_e, leak;
};

SimSensor SimulatedSensor(const v1::RigConfig& rig, const v1::CameraConfig& config, const CameraModel& model,
                          int bits) {
  const int sim_bits = bits == 8 ? 8 : 12;
  const double levels = std::ldexp(1.0, sim_bits) - 1;
  const double gain = rig.sim().full_well_e() / levels / std::pow(10.0, config.gain_db() / 20.0);
  // Crossed polarizers leak more the further the camera's axis turns from the design axis (+z).
  const double c = std::clamp(model.optical_axis().dot(Eigen::Vector3d(0, 0, -1)), -1.0, 1.0);
  return {rig.sim().full_on_electrons() / gain, gain, rig.sim().read_noise_e(),
          rig.sim().cross_leakage() + rig.sim().cross_leakage_growth() * (1 - c * c)};
}

}  // namespace

absl::StatusOr<CameraModel> CameraAtImageSize(const LoadedRig& rig, const std::string& camera_id, int width,
                                              int height, const CameraCalibration* calibration) {
  const v1::CameraConfig* config = nullptr;
  for (const v1::CameraConfig& c : rig.rig.cameras()) {
    if (c.id() == camera_id) config = &c;
  }
  if (config == nullptr) return absl::NotFoundError(absl::StrCat("camera \"", camera_id, "\" is not in the rig"));
  auto bad = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", camera_id, "\": ", what));
  };
  if (config->width() == 0 || width <= 0 || height <= 0) return bad("no image size");
  // The whole sensor: as calibrated, or the rig's nominal model.
  std::optional<CameraModel> sensor;
  if (calibration != nullptr) {
    const CameraModel* calibrated = calibration->Find(camera_id);
    if (calibrated == nullptr) {
      return absl::NotFoundError(absl::StrCat("camera \"", camera_id, "\" is not in the calibration (",
                                              calibration->source, ")"));
    }
    if (calibrated->width() != static_cast<int>(config->width()) ||
        calibrated->height() != static_cast<int>(config->height())) {
      return bad(absl::StrCat("its calibration (", calibration->source, ") is of a ", calibrated->width(), "x",
                              calibrated->height(), " sensor, the rig's of ", config->width(), "x", config->height()));
    }
    sensor = *calibrated;
  } else {
    auto m = CameraModel::FromConfig(*config, 1.0);
    if (!m.ok()) return m.status();
    sensor = *std::move(m);
  }
  // The frames' scale of the sensor is what the take recorded: a simulated camera renders at the take's render scale
  // (its size rounded in each axis), a real camera (or a fake GigE Vision camera, which scales its frames up to the
  // sensor) delivers the whole sensor. Never inferred from one axis: a size that rounds unevenly would not fit.
  const double render_scale = rig.rig.sim().has_render_scale() ? rig.rig.sim().render_scale() : 1.0;
  std::optional<CameraModel> model;
  std::vector<std::string> tried;
  for (double scale : {render_scale, 1.0}) {
    const CameraModel m = sensor->Scaled(scale);
    if (m.width() == width && m.height() == height) {
      model = m;
      break;
    }
    tried.push_back(
        absl::StrCat(m.width(), "x", m.height(),
                     scale == 1.0 ? " (the whole sensor)" : absl::StrCat(" at the take's render scale ", scale)));
  }
  if (!model) {
    return bad(absl::StrCat("its frames are ", width, "x", height, ", but its sensor of ", config->width(), "x",
                            config->height(), " gives ", absl::StrJoin(tried, " or ")));
  }
  return *model;
}

absl::StatusOr<CameraSetup> ResolveCamera(const LoadedRig& rig, const LightModel& light, const std::string& camera_id,
                                          int width, int height, int bits, const CameraCalibration* calibration) {
  auto model = CameraAtImageSize(rig, camera_id, width, height, calibration);
  if (!model.ok()) return model.status();
  const v1::CameraConfig* config = nullptr;
  for (const v1::CameraConfig& c : rig.rig.cameras()) {
    if (c.id() == camera_id) config = &c;
  }
  auto bad = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", camera_id, "\": ", what));
  };
  CameraSetup setup;
  setup.model = *model;
  PhotometricCamera& pc = setup.camera;
  pc.world_to_camera = model->rotation();
  pc.position_mm = model->position();
  pc.rays = model->PixelRays();

  const v1::PhotometricCalibration& cal = config->photometric();
  const bool simulated = config->backend() == v1::CAMERA_BACKEND_SIM;
  SimSensor sim{};
  if (simulated) sim = SimulatedSensor(rig.rig, *config, *model, bits);
  auto field = [&](bool has, double value, double derived, const char* name) -> absl::StatusOr<double> {
    if (has) return value;
    if (simulated) return derived;
    return bad(absl::StrCat("photometric.", name,
                            " is required for photometric processing (a real camera's "
                            "calibration; docs/processing.md#calibration)"));
  };
  auto white = field(cal.has_white_dn(), cal.white_dn(), sim.white_dn, "white_dn");
  if (!white.ok()) return white.status();
  auto gain = field(cal.has_electrons_per_dn(), cal.electrons_per_dn(), sim.electrons_per_dn, "electrons_per_dn");
  if (!gain.ok()) return gain.status();
  auto read = field(cal.has_read_noise_e(), cal.read_noise_e(), sim.read_noise_e, "read_noise_e");
  if (!read.ok()) return read.status();
  if (!(*white > 0)) return bad(absl::StrCat("photometric.white_dn ", *white, " must be > 0"));
  if (!(*gain > 0)) return bad(absl::StrCat("photometric.electrons_per_dn ", *gain, " must be > 0"));
  if (!(*read >= 0)) return bad(absl::StrCat("photometric.read_noise_e ", *read, " must be >= 0"));
  setup.black_level_dn = cal.black_level_dn();
  const double leak = cal.has_cross_leakage() ? cal.cross_leakage() : (simulated ? sim.leak : 0.0);
  if (!(leak >= 0 && leak < 1)) return bad(absl::StrCat("photometric.cross_leakage ", leak, " is not in [0, 1)"));
  if (!(setup.black_level_dn >= 0 && setup.black_level_dn < std::ldexp(1.0, bits) - 1)) {
    return bad(
        absl::StrCat("photometric.black_level_dn ", setup.black_level_dn, " is not below the ", bits, "-bit maximum"));
  }
  // White level: the full-on light a white surface facing the camera at the stage origin receives, in units of
  // n . H (light_model.h), with the full-on pattern's own weights.
  auto full_on = light.Find("cross-full");
  if (!full_on.ok()) return bad(absl::StrCat("the pattern set has no full-on: ", full_on.status().message()));
  const Eigen::Vector3d toward = model->position().normalized();
  const double full = light.DiffuseVector(*full_on, toward).dot(toward);
  if (!(full > 0)) return bad("no LED unit lights the side of the subject it sees");
  pc.white_scale = *white / full;
  pc.gain_e_per_dn = *gain;
  pc.read_noise_e = *read;
  // The simulator's 16-bit formats carry 12 bits, as most machine-vision sensors' do.
  const int data_bits = simulated && bits == 16 ? 12 : bits;
  pc.saturation_dn = std::ldexp(1.0, data_bits) - 1 - setup.black_level_dn;
  pc.cross_leak = leak;
  if (!cal.flat_field().empty()) {
    std::filesystem::path path(cal.flat_field());
    if (path.is_relative()) path = std::filesystem::path(rig.base_dir) / path;
    setup.flat_field = path.string();
  }
  const bool all_given = cal.has_white_dn() && cal.has_electrons_per_dn() && cal.has_read_noise_e();
  setup.source = all_given || !simulated ? "rig" : "simulator";
  return setup;
}

}  // namespace stage::processing
