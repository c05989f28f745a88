// gRPC ProcessingWorker service.
#include "worker_service.h"

#include <algorithm>
#include <chrono>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/metrics.h"
#include "stage/common/node_info.h"
#include "stage/processing/asset_dataset.h"
#include "stage/processing/asset_infer.h"
#include "stage/processing/asset_train.h"
#include "stage/processing/calibrate.h"
#include "stage/processing/mvs.h"
#include "stage/processing/photometric_stage.h"
#include "stage/processing/stabilize.h"
#include "stage/processing/template_fit.h"
#include "stage/processing/texture_fusion.h"

namespace stage::processing {

namespace {

// A job's last message: `units` done of `units`, where the results are, and what happened.
v1::ProcessingProgress Finished(int64_t units, const std::string& output_dir, const std::string& message) {
  v1::ProcessingProgress done;
  done.set_frames_done(units);
  done.set_frames_total(units);
  done.set_output_dir(output_dir);
  done.set_message(message);
  return done;
}

}  // namespace

grpc::Status WorkerService::GetInfo(grpc::ServerContext*, const v1::GetInfoRequest*, v1::NodeInfo* response) {
  *response = MakeNodeInfo(id_, v1::NODE_KIND_PROCESSING_WORKER, v1::CAMERA_ROLE_UNSPECIFIED, "local", rig_hash_);
  return grpc::Status::OK;
}

grpc::Status WorkerService::GetWorkerStatus(grpc::ServerContext*, const v1::GetWorkerStatusRequest*,
                                            v1::WorkerStatus* response) {
  response->set_jobs_completed(jobs_completed_.load());
  response->set_jobs_failed(jobs_failed_.load());
  response->set_threads(threads_);
  std::lock_guard<std::mutex> lock(mutex_);
  for (const v1::ProcessingJob* job : running_) *response->add_running() = *job;
  return grpc::Status::OK;
}

namespace {

// A finished job in the metrics: stage_processing_jobs_total{stage,outcome} and its time by stage.
void CountJob(v1::ProcessingStage stage, const char* outcome, double seconds) {
  std::string name = absl::AsciiStrToLower(v1::ProcessingStage_Name(stage));
  if (absl::StartsWith(name, "processing_stage_")) name = name.substr(17);
  auto& registry = metrics::Registry::Default();
  registry
      .GetCounter("stage_processing_jobs_total",
                  "Processing jobs finished, by stage and outcome (ok, failed, "
                  "cancelled)",
                  {{"stage", name}, {"outcome", outcome}})
      ->Increment();
  registry
      .GetHistogram("stage_processing_job_seconds", "Wall time of processing jobs, by stage",
                    metrics::ExponentialBounds(0.1, 2, 16), {{"stage", name}})
      ->Observe(seconds);
}

}  // namespace

grpc::Status WorkerService::Process(grpc::ServerContext* context, const v1::ProcessingJob* job,
                                    grpc::ServerWriter<v1::ProcessingProgress>* writer) {
  if (job->stage() != v1::PROCESSING_STAGE_PHOTOMETRIC && job->stage() != v1::PROCESSING_STAGE_CALIBRATION &&
      job->stage() != v1::PROCESSING_STAGE_MVS && job->stage() != v1::PROCESSING_STAGE_FIT &&
      job->stage() != v1::PROCESSING_STAGE_TEXTURES && job->stage() != v1::PROCESSING_STAGE_STABILIZE &&
      job->stage() != v1::PROCESSING_STAGE_ASSET_DATASET && job->stage() != v1::PROCESSING_STAGE_ASSET_TRAIN &&
      job->stage() != v1::PROCESSING_STAGE_ASSET_INFER && job->stage() != v1::PROCESSING_STAGE_GRAPH) {
    return ToGrpcStatus(absl::InvalidArgumentError(absl::StrCat(
        "worker \"", id_, "\": no stage ", v1::ProcessingStage_Name(job->stage()),
        " (stages: photometric, calibration, mvs, fit, textures, stabilize, asset dataset, asset train, asset "
        "infer, graph)")));
  }
  if (job->has_asset() && job->stage() != v1::PROCESSING_STAGE_ASSET_DATASET &&
      job->stage() != v1::PROCESSING_STAGE_ASSET_TRAIN) {
    return ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("worker \"", id_, "\": ", v1::ProcessingStage_Name(job->stage()), " takes no asset options")));
  }
  if (job->has_graph() && job->stage() != v1::PROCESSING_STAGE_GRAPH) {
    return ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("worker \"", id_, "\": ", v1::ProcessingStage_Name(job->stage()), " takes no graph request")));
  }
  if (job->take_dir().empty()) {
    return ToGrpcStatus(absl::InvalidArgumentError(absl::StrCat("worker \"", id_, "\": the job names no take")));
  }
  if (job->stabilize_method() != v1::STABILIZE_METHOD_UNSPECIFIED && job->stage() != v1::PROCESSING_STAGE_STABILIZE) {
    return ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("worker \"", id_, "\": ", v1::ProcessingStage_Name(job->stage()), " takes no stabilize_method (",
                     v1::StabilizeMethod_Name(job->stabilize_method()), ")")));
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    running_.push_back(job);
  }
  Logger("worker")->info("worker {}: {} on {} frames [{}, {})", id_, v1::ProcessingStage_Name(job->stage()),
                         job->take_dir(), job->first_frame(), job->last_frame());
  // The caller's cancel (the controller relays stagectl's Ctrl-C) stops the job between units.
  auto report = [&](const JobProgress& progress) {
    v1::ProcessingProgress m;
    m.set_frames_done(progress.done);
    m.set_frames_total(progress.total);
    m.set_message(progress.message);
    if (!context->IsCancelled()) writer->Write(m);
  };
  auto cancelled = [&] { return context->IsCancelled(); };
  const auto started = std::chrono::steady_clock::now();
  absl::StatusOr<v1::ProcessingProgress> result;
  switch (job->stage()) {
    case v1::PROCESSING_STAGE_CALIBRATION:
      result = RunCalibrationJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_MVS:
      result = RunMvsJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_FIT:
      result = RunFitJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_TEXTURES:
      result = RunTexturesJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_STABILIZE:
      result = RunStabilizeJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_ASSET_DATASET:
      result = RunAssetDatasetJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_ASSET_TRAIN:
      result = RunAssetTrainJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_ASSET_INFER:
      result = RunAssetInferJob(*job, report, cancelled);
      break;
    case v1::PROCESSING_STAGE_GRAPH:
      result = RunGraphJob(*job, report, cancelled);
      break;
    default:
      result = RunPhotometricJob(*job, report, cancelled);
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    running_.erase(std::find(running_.begin(), running_.end(), job));
  }
  CountJob(job->stage(),
           result.ok()              ? "ok"
           : context->IsCancelled() ? "cancelled"
                                    : "failed",
           std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count());
  if (!result.ok()) {
    ++jobs_failed_;
    Logger("worker")->warn("worker {}: {}", id_, result.status().message());
    return ToGrpcStatus(result.status());
  }
  ++jobs_completed_;
  result->set_finished(true);
  writer->Write(*result);
  return grpc::Status::OK;
}

namespace {

// Where a job's surfaces come from (photometric stereo's geometry, the fit's surfaces).
absl::StatusOr<GeometrySpec> GeometryOf(const v1::ProcessingJob& job) {
  GeometrySpec spec;
  switch (job.geometry_source()) {
    case v1::GEOMETRY_SOURCE_UNSPECIFIED:
    case v1::GEOMETRY_SOURCE_MVS:
      spec.source = GeometrySource::kMvs;
      break;
    case v1::GEOMETRY_SOURCE_NONE:
      spec.source = GeometrySource::kNone;
      break;
    case v1::GEOMETRY_SOURCE_DIRECTORY:
      spec.source = GeometrySource::kDirectory;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat("geometry_source: unknown value ", job.geometry_source()));
  }
  spec.dir = job.geometry();
  return spec;
}

// `value` into `field` where the job gives one (0: the default).
template <typename V, typename T>
void SetIfGiven(V value, T* field) {
  if (value != 0) *field = static_cast<T>(value);
}

}  // namespace

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunPhotometricJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  PhotometricJob p;
  p.take_dir = job.take_dir();
  p.first_frame = job.first_frame();
  p.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  p.cameras.assign(job.cameras().begin(), job.cameras().end());
  auto geometry = GeometryOf(job);
  if (!geometry.ok()) return geometry.status();
  p.geometry = *geometry;
  p.calibration = job.calibration();
  p.options.threads = static_cast<int>(threads_);
  auto result = RunPhotometric(p, progress, cancelled);
  if (!result.ok()) return result.status();
  return Finished(result->units, result->output_dir,
                  absl::StrCat(result->units, " camera frame(s) processed into ", result->output_dir));
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunCalibrationJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  if (!job.geometry().empty() || job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED ||
      !job.calibration().empty()) {
    return absl::InvalidArgumentError("calibration takes no geometry and no calibration");
  }
  CalibrationJob c;
  c.take_dir = job.take_dir();
  c.options.first_frame = job.first_frame();
  c.options.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  c.options.cameras.assign(job.cameras().begin(), job.cameras().end());
  auto report = RunCalibration(c, progress, cancelled);
  if (!report.ok()) return report.status();
  return Finished(static_cast<int64_t>(report->cameras.size()), report->output_dir, FormatCalibrationReport(*report));
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunMvsJob(const v1::ProcessingJob& job,
                                                                const std::function<void(const JobProgress&)>& progress,
                                                                const std::function<bool()>& cancelled) const {
  if (!job.geometry().empty() || job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED) {
    return absl::InvalidArgumentError("multi-view stereo takes no geometry: it makes it");
  }
  MvsJob m;
  m.take_dir = job.take_dir();
  m.first_frame = job.first_frame();
  m.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  m.cameras.assign(job.cameras().begin(), job.cameras().end());
  m.calibration = job.calibration();
  m.options.threads = static_cast<int>(threads_);
  auto result = RunMvs(m, progress, cancelled);
  if (!result.ok()) return result.status();
  return Finished(result->units, result->output_dir,
                  absl::StrCat(result->units, " frame(s) reconstructed into ", result->output_dir));
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunFitJob(const v1::ProcessingJob& job,
                                                                const std::function<void(const JobProgress&)>& progress,
                                                                const std::function<bool()>& cancelled) const {
  if (job.cameras_size() > 0 || !job.calibration().empty()) {
    return absl::InvalidArgumentError("the template fit takes no cameras and no calibration: it fits surfaces");
  }
  FitJob f;
  f.take_dir = job.take_dir();
  f.first_frame = job.first_frame();
  f.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  auto surface = GeometryOf(job);
  if (!surface.ok()) return surface.status();
  f.surface = *surface;
  auto result = RunFit(f, progress, cancelled);
  if (!result.ok()) return result.status();
  return Finished(result->units, result->output_dir,
                  absl::StrCat(result->units, " frame(s) fitted into ", result->output_dir));
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunTexturesJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  if (job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED || !job.geometry().empty()) {
    return absl::InvalidArgumentError("texture fusion takes no geometry: it reads the fit (run the fit stage first)");
  }
  TexturesJob t;
  t.take_dir = job.take_dir();
  t.first_frame = job.first_frame();
  t.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  t.cameras.assign(job.cameras().begin(), job.cameras().end());
  t.calibration = job.calibration();
  if (job.texture_size() != 0) t.options.size = job.texture_size();
  auto result = RunTextures(t, progress, cancelled);
  if (!result.ok()) return result.status();
  return Finished(result->units, result->output_dir,
                  absl::StrCat(result->units, " frame(s) of textures fused into ", result->output_dir));
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunStabilizeJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  if (job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED || !job.geometry().empty() ||
      !job.calibration().empty() || job.cameras_size() > 0 || job.texture_size() != 0) {
    return absl::InvalidArgumentError(
        "stabilization takes no geometry, calibration, cameras or texture size: it reads the fused textures");
  }
  StabilizeJob s;
  s.take_dir = job.take_dir();
  s.first_frame = job.first_frame();
  s.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  switch (job.stabilize_method()) {
    case v1::STABILIZE_METHOD_UNSPECIFIED:
    case v1::STABILIZE_METHOD_FLOW:
      s.options.method = StabilizeMethod::kFlow;
      break;
    case v1::STABILIZE_METHOD_UNET:
      s.options.method = StabilizeMethod::kUNet;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat("no stabilize_method ", job.stabilize_method()));
  }
  auto result = RunStabilize(s, progress, cancelled);
  if (!result.ok()) return result.status();
  return Finished(result->units, result->output_dir,
                  absl::StrCat(result->units, " frame(s) of textures stabilized into ", result->output_dir));
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunAssetDatasetJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  if (job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED || !job.geometry().empty()) {
    return absl::InvalidArgumentError("the asset's dataset takes no geometry: asset.source says");
  }
  const v1::AssetOptions& a = job.asset();
  if (a.iterations() != 0 || a.batch() != 0 || a.input_size() != 0 || a.levels() != 0 || a.base_channels() != 0 ||
      a.max_channels() != 0 || a.geometry_latent() != 0 || a.pose_latent() != 0 || a.seed() != 0 ||
      a.network() != v1::ASSET_NETWORK_UNSPECIFIED || a.expression_latent() != 0 || a.view_latent() != 0 ||
      a.held_out_cameras_size() > 0 || a.hidden() != 0 || a.layers() != 0 || a.texture_latent() != 0 ||
      a.direct_textures() || a.freeze_encoder() || a.region_weight() != 0 || a.map_loss() != 0 ||
      a.learning_rate() != 0 || a.has_jitter() || a.has_input_noise()) {
    return absl::InvalidArgumentError("the asset's dataset takes no training options (asset_train's)");
  }
  DatasetOptions d;
  d.take_dir = job.take_dir();
  d.first_frame = job.first_frame();
  d.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  d.source = a.source() == v1::ASSET_SOURCE_RECONSTRUCTION ? AssetSource::kReconstruction : AssetSource::kTruth;
  if (a.geometry_size() != 0) d.geometry_size = a.geometry_size();
  if (a.image_size() != 0) d.image_size = a.image_size();
  if (job.texture_size() != 0) d.texture_size = job.texture_size();  // taken where the source has textures
  d.neutral_texture_size = a.neutral_texture_size();
  SetIfGiven(a.frame_step(), &d.frame_step);
  SetIfGiven(a.crop_mm(), &d.crop_mm);
  if (a.has_held_out_fraction()) d.held_out_fraction = a.held_out_fraction();
  SetIfGiven(a.held_out_blocks(), &d.held_out_blocks);
  d.held_out_sequence = a.held_out_sequence();
  d.cameras.assign(job.cameras().begin(), job.cameras().end());
  d.calibration = job.calibration();
  d.progress = [&](int64_t done, int64_t total) { progress({done, total, "frames"}); };
  d.cancelled = cancelled;
  auto result = BuildAssetDataset(d);
  if (!result.ok()) return result.status();
  return Finished(result->frames, result->path,
                  absl::StrCat(result->frames, " frame(s) into the asset's dataset ", result->path));
}

namespace {

// A training job's progress: (step, steps, total loss); false stops it.
using TrainReport = std::function<bool(int64_t, int64_t, double)>;

// The options both VAEs' convolutional nets have (GeometryVaeOptions, ExpressionVaeOptions), where the job gives them.
template <typename Net>
void SetConvolutionalOptions(const v1::AssetOptions& a, Net* o) {
  SetIfGiven(a.input_size(), &o->input_size);
  SetIfGiven(a.levels(), &o->levels);
  SetIfGiven(a.base_channels(), &o->base_channels);
  SetIfGiven(a.max_channels(), &o->max_channels);
  SetIfGiven(a.seed(), &o->seed);
}

absl::StatusOr<v1::ProcessingProgress> TrainExpressionJob(const v1::AssetOptions& a, const std::string& dataset,
                                                          const TrainingSchedule& schedule, const TrainReport& report) {
  ExpressionTrainJob t;
  t.dataset = dataset;
  t.schedule = schedule;
  SetConvolutionalOptions(a, &t.expression);
  SetIfGiven(a.expression_latent(), &t.expression.expression_latent);
  SetIfGiven(a.view_latent(), &t.expression.view_latent);
  t.held_out_cameras.assign(a.held_out_cameras().begin(), a.held_out_cameras().end());
  t.progress = [&](int64_t step, int64_t total, const ExpressionLosses& l) { return report(step, total, l.total); };
  auto result = TrainExpressionAsset(t);
  if (!result.ok()) return result.status();
  return Finished(result->steps, result->output_dir,
                  absl::StrCat("expression VAE trained ", result->steps, " steps into ", result->output_dir, ": ",
                               ExpressionEvaluationJson(result->evaluation)));
}

absl::StatusOr<v1::ProcessingProgress> TrainMappingJob(const v1::AssetOptions& a, const std::string& dataset,
                                                       const TrainingSchedule& schedule, const TrainReport& report) {
  MappingTrainJob t;
  t.dataset = dataset;
  t.schedule = schedule;
  SetIfGiven(a.hidden(), &t.mapping.hidden);
  SetIfGiven(a.layers(), &t.mapping.layers);
  SetIfGiven(a.seed(), &t.mapping.seed);
  if (a.has_input_noise()) t.input_noise = a.input_noise();
  t.progress = report;
  auto result = TrainLatentMapping(t);
  if (!result.ok()) return result.status();
  return Finished(result->steps, result->output_dir,
                  absl::StrCat("latent mapping trained ", result->steps, " steps into ", result->output_dir, "\n",
                               FormatDrivenEvaluation(result->evaluation)));
}

absl::StatusOr<v1::ProcessingProgress> FineTuneJobOf(const v1::AssetOptions& a, const std::string& dataset,
                                                     const TrainingSchedule& schedule, const TrainReport& report) {
  FineTuneJob t;
  t.dataset = dataset;
  t.schedule = schedule;
  t.driving.train_encoder = !a.freeze_encoder();
  t.map_loss_region_weight = a.map_loss();
  if (a.has_jitter()) {
    t.jitter_scale = a.jitter().scale();
    t.jitter_rotation_deg = a.jitter().rotation_deg();
    t.jitter_shift = a.jitter().shift();
    t.jitter_gain = a.jitter().gain();
    t.jitter_noise = a.jitter().noise();
  }
  SetIfGiven(a.seed(), &t.seed);
  t.progress = report;
  auto result = FineTuneDrivingAsset(t);
  if (!result.ok()) return result.status();
  return Finished(result->steps, result->output_dir,
                  absl::StrCat("driving path fine-tuned ", result->steps, " steps into ", result->output_dir, "\n",
                               FormatDrivenEvaluation(result->evaluation)));
}

absl::StatusOr<v1::ProcessingProgress> TrainGeometryJob(const v1::AssetOptions& a, const std::string& dataset,
                                                        const TrainingSchedule& schedule, const TrainReport& report) {
  AssetTrainJob t;
  t.dataset = dataset;
  t.schedule = schedule;
  SetConvolutionalOptions(a, &t.geometry);
  SetIfGiven(a.geometry_latent(), &t.geometry.geometry_latent);
  SetIfGiven(a.pose_latent(), &t.geometry.pose_latent);
  if (a.region_weight() != 0) t.region_weight = a.region_weight();
  t.progress = [&](int64_t step, int64_t total, const GeometryLosses& l) { return report(step, total, l.total); };
  auto result = TrainGeometryAsset(t);
  if (!result.ok()) return result.status();
  return Finished(result->steps, result->output_dir,
                  absl::StrCat("geometry VAE trained ", result->steps, " steps into ", result->output_dir, "\n",
                               FormatTrainedEvaluation(result->evaluation)));
}

absl::StatusOr<v1::ProcessingProgress> TrainTextureJob(const v1::AssetOptions& a, const std::string& dataset,
                                                       const TrainingSchedule& schedule, const TrainReport& report) {
  TextureTrainJob t;
  t.dataset = dataset;
  t.schedule = schedule;
  SetConvolutionalOptions(a, &t.texture);
  SetIfGiven(a.texture_latent(), &t.texture.texture_latent);
  t.direct = a.direct_textures();
  t.progress = [&](int64_t step, int64_t total, const TextureLosses& l) { return report(step, total, l.total); };
  auto result = TrainTextureAsset(t);
  if (!result.ok()) return result.status();
  return Finished(result->steps, result->output_dir,
                  absl::StrCat("texture VAE trained ", result->steps, " steps into ", result->output_dir, "\n",
                               FormatTextureEvaluation(result->evaluation)));
}

absl::StatusOr<v1::ProcessingProgress> TrainTextureMappingJob(const v1::AssetOptions& a, const std::string& dataset,
                                                              const TrainingSchedule& schedule,
                                                              const TrainReport& report) {
  TextureMappingJob t;
  t.dataset = dataset;
  t.schedule = schedule;
  SetIfGiven(a.hidden(), &t.mapping.hidden);
  SetIfGiven(a.layers(), &t.mapping.layers);
  SetIfGiven(a.seed(), &t.mapping.seed);
  if (a.has_input_noise()) t.input_noise = a.input_noise();
  t.progress = report;
  auto result = TrainTextureMapping(t);
  if (!result.ok()) return result.status();
  return Finished(result->steps, result->output_dir,
                  absl::StrCat("texture mapping trained ", result->steps, " steps into ", result->output_dir, "\n",
                               FormatTextureDrivenEvaluation(result->evaluation)));
}

// Each network's own default schedule, as its job's.
TrainingSchedule DefaultSchedule(v1::AssetNetwork network) {
  switch (network) {
    case v1::ASSET_NETWORK_EXPRESSION:
      return ExpressionTrainJob{}.schedule;
    case v1::ASSET_NETWORK_MAPPING:
      return MappingTrainJob{}.schedule;
    case v1::ASSET_NETWORK_FINETUNE:
      return FineTuneJob{}.schedule;
    case v1::ASSET_NETWORK_TEXTURE:
      return TextureTrainJob{}.schedule;
    case v1::ASSET_NETWORK_TEXTURE_MAPPING:
      return TextureMappingJob{}.schedule;
    default:
      return AssetTrainJob{}.schedule;
  }
}

}  // namespace

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunAssetTrainJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  const v1::AssetOptions& a = job.asset();
  if (job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED || !job.geometry().empty() || job.texture_size() != 0 ||
      job.cameras_size() > 0 || !job.calibration().empty() || job.first_frame() != 0 || job.last_frame() != 0 ||
      a.source() != v1::ASSET_SOURCE_UNSPECIFIED || a.geometry_size() != 0 || a.image_size() != 0 ||
      a.neutral_texture_size() != 0 || a.frame_step() != 0 || a.crop_mm() != 0 || a.has_held_out_fraction() ||
      a.held_out_blocks() != 0 || !a.held_out_sequence().empty()) {
    return absl::InvalidArgumentError(
        "the asset's training takes no frames, cameras, calibration, geometry or dataset options: it reads "
        "TAKE/derived/asset/dataset.h5");
  }
  const std::string dataset = job.take_dir() + "/derived/asset/dataset.h5";
  const v1::AssetNetwork network =
      a.network() == v1::ASSET_NETWORK_UNSPECIFIED ? v1::ASSET_NETWORK_GEOMETRY : a.network();
  // Each option belongs to some of the networks; one given to another is refused, not ignored.
  const bool vae = network == v1::ASSET_NETWORK_GEOMETRY || network == v1::ASSET_NETWORK_EXPRESSION ||
                   network == v1::ASSET_NETWORK_TEXTURE;
  if ((!vae && (a.input_size() != 0 || a.levels() != 0 || a.base_channels() != 0 || a.max_channels() != 0)) ||
      (network != v1::ASSET_NETWORK_GEOMETRY &&
       (a.geometry_latent() != 0 || a.pose_latent() != 0 || a.region_weight() != 0)) ||
      (network != v1::ASSET_NETWORK_EXPRESSION &&
       (a.expression_latent() != 0 || a.view_latent() != 0 || a.held_out_cameras_size() > 0)) ||
      (network != v1::ASSET_NETWORK_MAPPING && network != v1::ASSET_NETWORK_TEXTURE_MAPPING &&
       (a.hidden() != 0 || a.layers() != 0)) ||
      (network != v1::ASSET_NETWORK_FINETUNE && (a.freeze_encoder() || a.map_loss() != 0 || a.has_jitter())) ||
      (network != v1::ASSET_NETWORK_MAPPING && network != v1::ASSET_NETWORK_TEXTURE_MAPPING && a.has_input_noise()) ||
      (network != v1::ASSET_NETWORK_TEXTURE && (a.texture_latent() != 0 || a.direct_textures()))) {
    return absl::InvalidArgumentError(absl::StrCat("asset training: an option given is not one of the ",
                                                   v1::AssetNetwork_Name(network), " network's"));
  }
  TrainingSchedule schedule = DefaultSchedule(network);
  if (a.iterations() != 0) schedule.iterations = a.iterations();
  if (a.batch() != 0) schedule.batch = a.batch();
  if (a.learning_rate() != 0) schedule.learning_rate = a.learning_rate();
  // The worker's jobs share its cores: torch's threads as the process's (SetTorchThreads); resumed where a job of the
  // same options, dataset and threads stopped, else started anew.
  schedule.resume = true;
  schedule.restart_if_different = true;
  const TrainReport report = [&](int64_t step, int64_t total, double loss) {
    if (step % 10 == 0 || step == total) progress({step, total, absl::StrCat("steps, loss ", loss)});
    return !cancelled();
  };
  if (network == v1::ASSET_NETWORK_EXPRESSION) return TrainExpressionJob(a, dataset, schedule, report);
  if (network == v1::ASSET_NETWORK_MAPPING) return TrainMappingJob(a, dataset, schedule, report);
  if (network == v1::ASSET_NETWORK_FINETUNE) return FineTuneJobOf(a, dataset, schedule, report);
  if (network == v1::ASSET_NETWORK_TEXTURE) return TrainTextureJob(a, dataset, schedule, report);
  if (network == v1::ASSET_NETWORK_TEXTURE_MAPPING) return TrainTextureMappingJob(a, dataset, schedule, report);
  return TrainGeometryJob(a, dataset, schedule, report);
}

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunAssetInferJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  if (job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED || !job.geometry().empty() || job.texture_size() != 0 ||
      !job.calibration().empty() || job.has_asset()) {
    return absl::InvalidArgumentError(
        "the asset's inference takes one camera and frames only: it reads the asset of TAKE/derived/asset");
  }
  if (job.cameras_size() != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("the asset's inference drives it from one camera: the job names ", job.cameras_size()));
  }
  AssetInferOptions o;
  o.dataset = job.take_dir() + "/derived/asset/dataset.h5";
  o.camera = job.cameras(0);
  o.take_dir = job.take_dir();
  o.first_frame = job.first_frame();
  o.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  o.progress = [&](int64_t done) { progress({done, 0, "frames driven"}); };
  o.cancelled = cancelled;
  auto result = InferAsset(o);
  if (!result.ok()) return result.status();
  return Finished(
      static_cast<int64_t>(result->frames.size()), result->output_dir,
      absl::StrCat(result->frames.size(), " frame(s) of ", o.camera, " drove the asset into ", result->output_dir));
}

}  // namespace stage::processing
