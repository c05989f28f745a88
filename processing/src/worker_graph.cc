// The ProcessingWorker's graph job (PROCESSING_STAGE_GRAPH): the processing graph over a take on this machine, its
// tasks run by the local executor, each line of the run streamed as progress.
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/status.h"
#include "stage/processing/graph_executor.h"
#include "worker_service.h"

namespace stage::processing {
namespace {

absl::StatusOr<GraphStage> GraphStageOf(v1::ProcessingStage stage) {
  switch (stage) {
    case v1::PROCESSING_STAGE_CALIBRATION:
      return GraphStage::kCalibration;
    case v1::PROCESSING_STAGE_MVS:
      return GraphStage::kMvs;
    case v1::PROCESSING_STAGE_PHOTOMETRIC:
      return GraphStage::kPhotometric;
    case v1::PROCESSING_STAGE_FIT:
      return GraphStage::kFit;
    case v1::PROCESSING_STAGE_TEXTURES:
      return GraphStage::kTextures;
    case v1::PROCESSING_STAGE_STABILIZE:
      return GraphStage::kStabilize;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat(v1::ProcessingStage_Name(stage),
                       " is not a stage of the processing graph (calibration, mvs, photometric, fit, textures, "
                       "stabilize)"));
  }
}

absl::StatusOr<GraphOptions> GraphOptionsOf(const v1::ProcessingJob& job) {
  if (job.cameras_size() > 0 || !job.geometry().empty() || job.geometry_source() != v1::GEOMETRY_SOURCE_UNSPECIFIED ||
      job.texture_size() != 0 || job.has_asset()) {
    return absl::InvalidArgumentError(
        "PROCESSING_STAGE_GRAPH takes no cameras, geometry, texture size or asset options: a stage's own flags go in "
        "graph.flags");
  }
  const v1::GraphRequest& g = job.graph();
  GraphOptions o;
  o.take_dir = job.take_dir();
  o.first_frame = job.first_frame();
  o.last_frame = job.last_frame() > 0 ? job.last_frame() : -1;
  o.calibration = job.calibration();
  for (int s : g.stages()) {
    STAGE_ASSIGN_OR_RETURN(GraphStage stage, GraphStageOf(static_cast<v1::ProcessingStage>(s)));
    o.stages.push_back(stage);
  }
  if (g.chunk_frames() != 0) o.chunk_frames = g.chunk_frames();
  o.retries = g.retries();
  for (const v1::StageFlags& f : g.flags()) {
    STAGE_ASSIGN_OR_RETURN(GraphStage stage, GraphStageOf(f.stage()));
    o.stage_args[stage].insert(o.stage_args[stage].end(), f.args().begin(), f.args().end());
  }
  STAGE_RETURN_IF_ERROR(o.Validate());
  return o;
}

}  // namespace

absl::StatusOr<v1::ProcessingProgress> WorkerService::RunGraphJob(
    const v1::ProcessingJob& job, const std::function<void(const JobProgress&)>& progress,
    const std::function<bool()>& cancelled) const {
  STAGE_ASSIGN_OR_RETURN(const GraphOptions options, GraphOptionsOf(job));
  LocalExecutorOptions local;
  local.jobs = job.graph().jobs() > 0 ? job.graph().jobs() : 1;
  STAGE_RETURN_IF_ERROR(local.Validate());
  std::unique_ptr<GraphExecutor> executor = MakeLocalExecutor(local);
  auto report = RunGraph(
      options, *executor,
      [&](const std::string& line) {
        if (progress) progress(JobProgress{0, 0, line});
      },
      cancelled);
  if (!report.ok()) return report.status();
  v1::ProcessingProgress done;
  done.set_output_dir(report->plan.run_dir);
  std::vector<std::string> stages;
  for (const StageProgress& p : report->stages) {
    done.set_frames_done(done.frames_done() + p.up_to_date);
    done.set_frames_total(done.frames_total() + p.units);
    stages.push_back(absl::StrCat(GraphStageName(p.stage), " ", p.up_to_date, "/", p.units));
  }
  if (!report->ok()) {
    std::vector<std::string> failed;
    for (const TaskFailure& f : report->failures) {
      failed.push_back(absl::StrCat(f.task, " ", TaskStateName(f.state), ": ", f.message, " (log: ", f.log, ")"));
    }
    return absl::AbortedError(absl::StrCat("processing graph: ", report->failures.size(),
                                           " task(s) did not finish: ", absl::StrJoin(failed, "; ")));
  }
  done.set_message(report->nothing_to_do
                       ? "every output asked for is up to date: nothing to do"
                       : absl::StrCat("processed (", report->plan.needed_tasks(),
                                      " task(s)): ", absl::StrJoin(stages, ", "), " units up to date"));
  return done;
}

}  // namespace stage::processing
