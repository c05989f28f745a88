// gRPC ProcessingWorker service.
#include "worker_service.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "stage/common/grpc_status.h"
#include "stage/common/logging.h"
#include "stage/common/node_info.h"
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

grpc::Status WorkerService::Process(grpc::ServerContext* context, const v1::ProcessingJob* job,
                                    grpc::ServerWriter<v1::ProcessingProgress>* writer) {
  if (job->stage() != v1::PROCESSING_STAGE_PHOTOMETRIC && job->stage() != v1::PROCESSING_STAGE_CALIBRATION &&
      job->stage() != v1::PROCESSING_STAGE_MVS && job->stage() != v1::PROCESSING_STAGE_FIT &&
      job->stage() != v1::PROCESSING_STAGE_TEXTURES && job->stage() != v1::PROCESSING_STAGE_STABILIZE) {
    return ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("worker \"", id_, "\": no stage ", v1::ProcessingStage_Name(job->stage()),
                     " (stages: photometric, calibration, mvs, fit, textures, stabilize)")));
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
    default:
      result = RunPhotometricJob(*job, report, cancelled);
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    running_.erase(std::find(running_.begin(), running_.end(), job));
  }
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

}  // namespace stage::processing
