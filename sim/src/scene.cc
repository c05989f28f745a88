// The simulated stage derived from the rig, and per-camera rendering.
#include "stage/sim/scene.h"

#include <malloc.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <mutex>
#include <random>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/logging.h"
#include "stage/common/status.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"

namespace stage::sim {
namespace {

Material AnalyticMaterial(const v1::SimSubject& config) {
  Material m;
  if (config.albedo_size() == 3) {
    m.albedo = Eigen::Vector3f(static_cast<float>(config.albedo(0)), static_cast<float>(config.albedo(1)),
                               static_cast<float>(config.albedo(2)));
  }
  m.specular = static_cast<float>(config.specular());
  m.roughness = static_cast<float>(config.roughness());
  return m;
}

}  // namespace

absl::Status SensorFormat(const std::string& f, int* bits, std::string* mosaic) {
  if (f == "RGB8" || f.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("pixel format \"", f, "\": the simulated sensor gives Mono or Bayer formats only"));
  }
  *bits = absl::EndsWith(f, "8") ? 8 : absl::EndsWith(f, "16") ? 16 : 12;
  if (absl::StartsWith(f, "Mono")) {
    *mosaic = "mono";
  } else if (absl::StartsWith(f, "Bayer") && f.size() >= 7) {
    *mosaic = f.substr(5, 2);
  } else {
    return absl::InvalidArgumentError(absl::StrCat("pixel format \"", f, "\" is not a Mono or Bayer format"));
  }
  return absl::OkStatus();
}

std::vector<uint8_t> PackRaw(const RawImage& raw, const std::string& pixel_format) {
  const bool wide = !absl::EndsWith(pixel_format, "8");
  std::vector<uint8_t> out(raw.data.size() * (wide ? 2 : 1));
  if (!wide) {
    for (size_t i = 0; i < raw.data.size(); ++i) out[i] = static_cast<uint8_t>(raw.data[i]);
  } else {
    for (size_t i = 0; i < raw.data.size(); ++i) {
      out[2 * i] = static_cast<uint8_t>(raw.data[i] & 0xff);
      out[2 * i + 1] = static_cast<uint8_t>(raw.data[i] >> 8);
    }
  }
  return out;
}

absl::StatusOr<std::shared_ptr<const SimScene>> SimScene::FromLoadedRig(const LoadedRig& loaded) {
  STAGE_ASSIGN_OR_RETURN(timing::PatternSet patterns, timing::LoadRigPatternSet(loaded.rig, loaded.base_dir));
  return Create(loaded.rig, patterns, loaded.base_dir);
}

absl::Status SimScene::MakeSubject(const std::string& base_dir) {
  const v1::SimSubject& config = rig_.sim().subject();
  const float size = static_cast<float>(config.size_mm());
  if (config.kind() == "sphere") {
    still_ = std::make_shared<SphereSubject>(Eigen::Vector3f::Zero(), size, AnalyticMaterial(config));
    return absl::OkStatus();
  }
  if (config.kind() == "plane") {
    still_ = std::make_shared<PlaneSubject>(Eigen::Vector3f::Zero(), Eigen::Vector3f::UnitZ(), size,
                                            AnalyticMaterial(config));
    return absl::OkStatus();
  }
  auto resolve = [&](const std::string& file) {
    std::filesystem::path path(file);
    if (path.is_relative() && !base_dir.empty()) path = std::filesystem::path(base_dir) / path;
    return path.string();
  };
  if (config.kind() == "charuco") {
    STAGE_ASSIGN_OR_RETURN(board_, BoardModel::Create(config.board()));
    model_ = board_;
  } else if (config.kind() != "head") {
    return absl::InvalidArgumentError(
        absl::StrCat("sim.subject.kind: \"", config.kind(), "\" is not a subject kind (head, sphere, plane, charuco)"));
  } else if (!config.asset().neutral_obj().empty()) {
    const v1::SimHeadAsset& asset = config.asset();
    HeadAssetFiles files;
    files.neutral_obj = resolve(asset.neutral_obj());
    for (const auto& [name, file] : asset.blendshapes()) files.blendshapes.emplace_back(name, resolve(file));
    std::sort(files.blendshapes.begin(), files.blendshapes.end());
    files.albedo = resolve(asset.albedo());
    if (!asset.specular().empty()) files.specular = resolve(asset.specular());
    if (!asset.roughness().empty()) files.roughness = resolve(asset.roughness());
    if (!asset.normal().empty()) files.normal = resolve(asset.normal());
    files.specular_value = static_cast<float>(config.specular());
    files.roughness_value = static_cast<float>(config.roughness());
    files.specular_scale = static_cast<float>(asset.specular_scale());
    files.units_mm = static_cast<float>(asset.units_mm());
    if (asset.pivot_mm_size() == 3) {
      files.pivot_mm = Eigen::Vector3d(asset.pivot_mm(0), asset.pivot_mm(1), asset.pivot_mm(2)).cast<float>();
    }
    STAGE_ASSIGN_OR_RETURN(head_, HeadModel::FromAsset(files));
    for (const std::string& note : head_->notes()) Logger("sim")->warn("{}", note);
    model_ = head_;
  } else {
    head_ = HeadModel::Procedural(rig_.sim().seed(), static_cast<int>(config.head_resolution()),
                                  HeadShape::Drawn(config.identity()), static_cast<float>(config.blood_flow()));
    model_ = head_;
  }
  if (config.performance() == "default") {
    performance_ = board_ != nullptr ? BoardSequence() : Performance::Default();
  } else if (config.performance() == "still") {
    performance_.keys = {{0.0, HeadPose{}}};
  } else if (config.performance() == "range_of_motion") {
    if (board_ != nullptr) {
      return absl::InvalidArgumentError("sim.subject.performance: \"range_of_motion\" is a head's, not the board's");
    }
    performance_ = Performance::RangeOfMotion(rig_.sim().seed(), kRangeOfMotionS);
  } else {
    STAGE_ASSIGN_OR_RETURN(performance_, Performance::FromYaml(resolve(config.performance())));
  }
  if (!animated()) still_ = model_->Posed(performance_.At(0));
  return absl::OkStatus();
}

absl::Status SimScene::CheckFault(const v1::SimFault& fault) const {
  v1::RigConfig rig = rig_;
  rig.mutable_sim()->clear_faults();
  *rig.mutable_sim()->add_faults() = fault;
  constexpr absl::string_view kPath = "sim.faults[0]";
  for (const RigError& e : ValidateRig(rig, "")) {
    if (absl::StartsWith(e.path, kPath)) {
      return absl::InvalidArgumentError(absl::StrCat("fault", e.path.substr(kPath.size()), ": ", e.message));
    }
  }
  return absl::OkStatus();
}

HeadPose SimScene::PoseAt(int64_t frame) const {
  if (model_ == nullptr) return {};
  const double cycle_s = static_cast<double>(timing::CycleLength(schedule_)) / base_.slot_rate_hz();
  return performance_.At((static_cast<double>(frame) + 0.5) * cycle_s);
}

std::string SimScene::SequenceAt(int64_t frame) const {
  if (model_ == nullptr) return "";
  const double cycle_s = static_cast<double>(timing::CycleLength(schedule_)) / base_.slot_rate_hz();
  return performance_.SequenceAt((static_cast<double>(frame) + 0.5) * cycle_s);
}

std::shared_ptr<const Subject> SimScene::SubjectAt(int64_t frame) const {
  if (!animated()) return still_;
  std::lock_guard<std::mutex> lock(cache_mutex_);
  for (const auto& [f, subject] : cache_) {
    if (f == frame) return subject;
  }
  std::shared_ptr<const Subject> posed = model_->Posed(PoseAt(frame));
  cache_.emplace_back(frame, posed);
  if (cache_.size() > 4) cache_.erase(cache_.begin());
  return posed;
}

absl::StatusOr<CameraModel> DeviatedCamera(const CameraModel& nominal, const v1::SimCameraDeviation& deviation,
                                           uint64_t seed, int index) {
  // One stream per camera, apart from every other use of the seed.
  std::seed_seq seq{static_cast<uint32_t>(seed), static_cast<uint32_t>(seed >> 32), static_cast<uint32_t>(index),
                    0xca11b7u};
  std::mt19937_64 rng(seq);
  std::normal_distribution<double> normal(0.0, 1.0);
  // One draw a statement, in a fixed order (the order in which arguments are evaluated is the compiler's).
  auto draw = [&](double sigma) { return deviation.scale() * sigma * normal(rng); };
  CameraParameters p = nominal.parameters();
  Eigen::Vector3d turn;
  for (int k = 2; k >= 0; --k) turn[k] = draw(deviation.rotation_deg());  // z, y, x
  const double angle = turn.norm() * M_PI / 180;
  if (angle > 0) p.rotation = Eigen::AngleAxisd(angle, turn.normalized()).toRotationMatrix() * p.rotation;
  for (int k = 0; k < 3; ++k) p.position[k] += draw(deviation.position_mm());
  const double focal = 1 + draw(deviation.focal());
  p.fx *= focal;
  p.fy *= focal;
  p.cx += draw(deviation.principal_px());
  p.cy += draw(deviation.principal_px());
  p.distortion[0] += draw(deviation.radial());
  p.distortion[1] += draw(deviation.radial2());
  p.distortion[2] += draw(deviation.tangential());
  p.distortion[3] += draw(deviation.tangential());
  return CameraModel::FromParameters(p);
}

absl::StatusOr<std::shared_ptr<const SimScene>> SimScene::Create(const v1::RigConfig& rig,
                                                                 const timing::PatternSet& patterns,
                                                                 const std::string& base_dir) {
  std::shared_ptr<SimScene> scene(new SimScene());
  scene->rig_ = rig;
  scene->true_cameras_.source = "simulator truth";
  STAGE_ASSIGN_OR_RETURN(scene->schedule_, timing::CompileSchedule(rig, patterns));
  scene->base_ = timing::TimeBase::FromProto(scene->schedule_.time_base());
  scene->dome_ = Dome::FromRig(rig, rig.sim().dome_radius_mm());
  STAGE_RETURN_IF_ERROR(scene->MakeSubject(base_dir));
  for (int i = 0; i < rig.cameras_size(); ++i) {
    const v1::CameraConfig& c = rig.cameras(i);
    STAGE_ASSIGN_OR_RETURN(CameraModel nominal, CameraModel::FromConfig(c, 1.0));
    auto truth = DeviatedCamera(nominal, rig.sim().camera_deviation(), rig.sim().seed(), i);
    if (!truth.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("camera \"", c.id(), "\": sim.camera_deviation: ", truth.status().message()));
    }
    scene->true_cameras_.cameras.push_back({c.id(), *truth});
    const CameraModel model = truth->Scaled(rig.sim().render_scale());
    scene->leakages_.push_back(CrossLeakage(model, rig.sim().cross_leakage(), rig.sim().cross_leakage_growth()));
    SensorParams sensor;
    sensor.full_well_e = rig.sim().full_well_e();
    sensor.read_noise_e = rig.sim().read_noise_e();
    // Gain from the rig (dB of amplification over unity: fewer electrons per DN).
    const std::string format = PixelFormatName(c.pixel_format());
    if (auto s = SensorFormat(format, &sensor.bits, &sensor.mosaic); !s.ok()) {
      return absl::InvalidArgumentError(absl::StrCat("camera \"", c.id(), "\": ", s.message()));
    }
    // 16-bit formats carry 12-bit data, as most machine-vision sensors' do.
    if (sensor.bits == 16) sensor.bits = 12;
    sensor.electrons_per_dn = sensor.Gain() / std::pow(10.0, c.gain_db() / 20.0);
    // Sensitivity: a white Lambertian patch at the head centre facing the camera, lit by every unit's cross emitter.
    const Eigen::Vector3d n = model.position().normalized();
    double radiance = 0;
    for (const LedUnitModel& u : scene->dome_.units) {
      const double d2 = u.position.squaredNorm();
      radiance += 0.5 * std::max(0.0, n.dot(u.direction)) * u.intensity / (M_PI * d2);
    }
    const double exposure_s = c.exposure_us() * 1e-6;
    if (!(radiance > 0) || !(exposure_s > 0)) {
      return absl::InvalidArgumentError(
          absl::StrCat("camera \"", c.id(), "\": no LED unit lights the side of the subject it sees"));
    }
    sensor.electrons_per_radiance_s = rig.sim().full_on_electrons() / (radiance * exposure_s);
    scene->sensors_.push_back(sensor);
    scene->cameras_.push_back(std::move(model));
  }
  return std::shared_ptr<const SimScene>(std::move(scene));
}

int SimScene::CameraIndex(const std::string& id) const {
  for (int i = 0; i < rig_.cameras_size(); ++i) {
    if (rig_.cameras(i).id() == id) return i;
  }
  return -1;
}

int SimScene::LightNodeIndex(const std::string& id) const {
  for (int i = 0; i < rig_.light_nodes_size(); ++i) {
    if (rig_.light_nodes(i).id() == id) return i;
  }
  return -1;
}

WorldOptions SimScene::MakeWorldOptions(bool lockstep, int64_t t0_ns) const {
  WorldOptions o;
  o.slot_rate_hz = base_.slot_rate_hz();
  o.lockstep = lockstep;
  o.t0_ns = t0_ns;
  for (const v1::LightNodeTiming& n : schedule_.light_nodes()) {
    o.rise_ns.push_back(base_.TicksToNs(n.rise_ticks()));
    o.fall_ns.push_back(base_.TicksToNs(n.fall_ticks()));
  }
  return o;
}

std::vector<int> SimScene::FullOnPatterns() const {
  std::vector<int> out;
  for (int p = 0; p < schedule_.patterns_size(); ++p) {
    const EmitterLevels levels = PatternLevels(p);
    const bool parallel = schedule_.patterns(p).polarization() == v1::POLARIZATION_PARALLEL;
    const Eigen::VectorXf& lit = parallel ? levels.parallel : levels.cross;
    if (lit.size() > 0 && lit.minCoeff() > 0.999f) out.push_back(p);
  }
  return out;
}

EmitterLevels SimScene::PatternLevels(int64_t pattern, int dark_node) const {
  const auto n = static_cast<Eigen::Index>(dome_.units.size());
  EmitterLevels levels{Eigen::VectorXf::Zero(n), Eigen::VectorXf::Zero(n)};
  for (Eigen::Index l = 0; l < n; ++l) {
    const LedUnitModel& u = dome_.units[static_cast<size_t>(l)];
    if (u.node == dark_node) continue;
    const v1::PatternRow& row = schedule_.light_nodes(u.node).table().rows(static_cast<int>(pattern));
    levels.cross[l] = static_cast<float>(row.levels(static_cast<int>(u.cross_channel)) / 65535.0);
    levels.parallel[l] = static_cast<float>(row.levels(static_cast<int>(u.parallel_channel)) / 65535.0);
  }
  return levels;
}

v1::SimFault SimScene::Fault(const std::string& id) const {
  v1::SimFault merged;
  for (const v1::SimFault& f : rig_.sim().faults()) {
    if (f.target() == id) merged.MergeFrom(f);
  }
  return merged;
}

int64_t SimScene::SwitchDelayNs(int light_node) const {
  return base_.TicksToNs(schedule_.light_nodes(light_node).switch_ticks());
}

// A moving subject's responses are a new matrix of tens of MB per camera and pose. glibc gives blocks that large
// fresh pages from mmap and unmaps them when freed, so every pose paid the kernel's page faults and zeroing: half of a
// ChArUco take's render (0.47 s a camera frame, 0.24 s with this). Kept in the heap instead, they are reused. The
// setting is the process's: the processes that render (stage-sim-render, a camera node with the sim backend) do little
// else.
namespace {
void KeepLargeBlocksInTheHeap() {
  static std::once_flag once;
  std::call_once(once, [] {
    mallopt(M_MMAP_THRESHOLD, 1 << 30);
    mallopt(M_TRIM_THRESHOLD, std::numeric_limits<int>::max());
  });
}
}  // namespace

CameraRenderer::CameraRenderer(std::shared_ptr<const SimScene> scene, int camera_index, int threads)
    : scene_(std::move(scene)),
      index_(camera_index),
      threads_(threads),
      rays_(scene_->camera(camera_index)),
      stream_(Fnv1a64(scene_->rig().cameras(camera_index).id())) {
  KeepLargeBlocksInTheHeap();
}

std::shared_ptr<const PixelResponses> CameraRenderer::Responses(int64_t pose_frame) {
  if (!scene_->animated()) pose_frame = 0;
  std::lock_guard<std::mutex> lock(mutex_);
  if (responses_ == nullptr || responses_frame_ != pose_frame) {
    compute_.done.store(0);
    compute_.total.store(0);
    computing_frame_.store(pose_frame);
    auto subject = scene_->SubjectAt(pose_frame);
    responses_ = std::make_shared<const PixelResponses>(
        ComputeResponses(rays_, *subject, scene_->dome(), threads_, static_cast<int>(scene_->rig().sim().supersample()),
                         &compute_, static_cast<int>(scene_->rig().sim().texture_samples()), basis_));
    responses_frame_ = pose_frame;
    work_before_.fetch_add(compute_.done.exchange(0));  // counted once, whenever a reader looks
    computing_frame_.store(-1);
  }
  return responses_;
}

void CameraRenderer::ExpectOnly(std::vector<EmitterLevels> levels) {
  std::shared_ptr<ExposureBasis> basis;
  if (!levels.empty() && levels.size() < scene_->dome().units.size()) {
    basis = std::make_shared<ExposureBasis>();
    basis->levels = std::move(levels);
    basis->leakage = scene_->leakage(index_);
  }
  std::lock_guard<std::mutex> lock(mutex_);
  basis_ = std::move(basis);
  responses_ = nullptr;
}

void CameraRenderer::KeepRays(size_t budget_bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  rays_ = CameraRays(scene_->camera(index_), budget_bytes);
}

RawImage CameraRenderer::Render(const EmitterLevels& levels, double exposure_s, uint64_t counter, int64_t pose_frame) {
  std::shared_ptr<const PixelResponses> r = Responses(pose_frame);
  absl::StatusOr<std::vector<float>> radiance = RenderRadianceOf(*r, levels, scene_->leakage(index_));
  // Only sums under a basis refuse an exposure: the basis that missed goes (once, should two threads miss it
  // together), and with it the pose's sums; the pose's responses to every unit render any exposure.
  while (!radiance.ok()) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (basis_ != nullptr && basis_ == r->basis) {
        Logger("sim.render")
            ->warn(
                "camera {}: {} (the lights did not show one of the patterns it expected); rendering from every "
                "unit's responses from now on",
                scene_->rig().cameras(index_).id(), radiance.status().message());
        basis_ = nullptr;
        responses_ = nullptr;
      }
    }
    r = Responses(pose_frame);
    radiance = RenderRadianceOf(*r, levels, scene_->leakage(index_));
  }
  const std::vector<float>& rgb = *radiance;
  RawImage raw = ExposeSensor(rgb, r->width, r->height, exposure_s, scene_->sensor(index_), scene_->rig().sim().seed(),
                              stream_, counter);
  work_before_.fetch_add(1);
  return raw;
}

CameraRenderer::Progress CameraRenderer::progress() const {
  Progress p;
  const int64_t frame = computing_frame_.load();
  const uint64_t done = compute_.done.load(), total = compute_.total.load();
  p.work = work_before_.load() + done;
  if (frame >= 0) {
    p.activity = total > 0
                     ? absl::StrFormat("precomputing the subject's pose of frame %d: %.0f %%", frame,
                                       100.0 * static_cast<double>(std::min(done, total)) / static_cast<double>(total))
                     : absl::StrFormat("posing the subject for frame %d", frame);
  }
  return p;
}

}  // namespace stage::sim
