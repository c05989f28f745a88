// A network's resumable training: see training_run.h.
#include "training_run.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "stage/common/file_util.h"
#include "stage/common/logging.h"
#include "stage/common/status.h"

namespace stage::processing::internal {
namespace {

namespace fs = std::filesystem;
constexpr double kPi = 3.14159265358979323846;
using Losses = std::vector<std::vector<double>>;

// The curves of the first three losses, log scale, each smoothed over 1 % of the run.
cv::Mat PlotLosses(const Losses& losses, const std::vector<std::string>& names) {
  constexpr int kW = 800, kH = 400, kPad = 40;
  cv::Mat plot(kH, kW, CV_8UC3, cv::Scalar(255, 255, 255));
  if (losses.empty()) return plot;
  const std::vector<std::pair<const char*, cv::Scalar>> colours = {
      {"black", {0, 0, 0}}, {"blue", {200, 80, 0}}, {"green", {0, 140, 0}}};
  const size_t curves = std::min(colours.size(), names.size());
  double lo = INFINITY, hi = -INFINITY;
  for (const auto& l : losses) {
    for (size_t c = 0; c < curves; ++c) {
      if (l[c] > 0) lo = std::min(lo, std::log10(l[c])), hi = std::max(hi, std::log10(l[c]));
    }
  }
  if (!std::isfinite(lo)) lo = -1;
  if (!(hi > lo)) hi = lo + 1;
  const size_t window = std::max<size_t>(1, losses.size() / 100);
  std::string legend;
  for (size_t c = 0; c < curves; ++c) {
    std::vector<cv::Point> points;
    for (size_t i = 0; i < losses.size(); i += window) {
      double sum = 0;
      int n = 0;
      for (size_t j = i; j < std::min(losses.size(), i + window); ++j) sum += losses[j][c], ++n;
      const double v = std::log10(std::max(1e-12, sum / n));
      points.emplace_back(kPad + static_cast<int>((kW - 2 * kPad) * i / std::max<size_t>(1, losses.size() - 1)),
                          kH - kPad - static_cast<int>((kH - 2 * kPad) * (v - lo) / (hi - lo)));
    }
    cv::polylines(plot, points, false, colours[c].second, 1, cv::LINE_AA);
    absl::StrAppend(&legend, c == 0 ? "" : ", ", names[c], " ", colours[c].first);
  }
  cv::putText(plot, absl::StrFormat("loss (log10 %.2f .. %.2f): %s", lo, hi, legend), {kPad, 25},
              cv::FONT_HERSHEY_SIMPLEX, 0.5, {0, 0, 0}, 1, cv::LINE_AA);
  cv::putText(plot, absl::StrCat("step 1 .. ", losses.size()), {kPad, kH - 12}, cv::FONT_HERSHEY_SIMPLEX, 0.5,
              {0, 0, 0}, 1, cv::LINE_AA);
  return plot;
}

absl::Status WriteLosses(const std::string& dir, const Losses& losses, const std::vector<std::string>& names) {
  std::string csv = absl::StrCat("step,", absl::StrJoin(names, ","), "\n");
  for (size_t i = 0; i < losses.size(); ++i) {
    absl::StrAppend(&csv, i + 1);
    for (double v : losses[i]) absl::StrAppendFormat(&csv, ",%.17g", v);
    csv += "\n";
  }
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(dir + "/loss.csv", csv));
  const std::string tmp = dir + "/loss.tmp.png";
  if (!cv::imwrite(tmp, PlotLosses(losses, names))) return absl::UnavailableError(absl::StrCat(tmp, ": cannot write"));
  std::error_code ec;
  fs::rename(tmp, dir + "/loss.png", ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, "/loss.png: ", ec.message()));
  return absl::OkStatus();
}

absl::StatusOr<Losses> ReadLosses(const std::string& path, int64_t steps, const std::vector<std::string>& names) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": missing (the run's losses)"));
  const std::string header = absl::StrCat("step,", absl::StrJoin(names, ","));
  Losses out;
  std::string line;
  std::getline(in, line);
  if (line != header) return absl::InvalidArgumentError(absl::StrCat(path, ": its header is not ", header));
  while (static_cast<int64_t>(out.size()) < steps && std::getline(in, line)) {
    const std::vector<std::string> fields = absl::StrSplit(line, ',');
    std::vector<double> l;
    for (size_t i = 1; i < fields.size(); ++i) {
      char* end = nullptr;
      l.push_back(std::strtod(fields[i].c_str(), &end));
      if (end == fields[i].c_str() || *end != '\0') l.clear(), i = fields.size();
    }
    if (fields.size() != names.size() + 1 || l.size() != names.size()) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": line \"", line, "\" is not ", header));
    }
    out.push_back(std::move(l));
  }
  if (static_cast<int64_t>(out.size()) != steps) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": holds ", out.size(), " steps, the checkpoint ", steps));
  }
  return out;
}

std::string CheckpointName(int64_t step) { return absl::StrFormat("checkpoint-%06d.pt", step); }

// The run's state at `step`: the net in a file of the step's own, the losses, then trainer.json naming that file (the
// state counts once it is renamed into place), then the previous checkpoint removed.
absl::Status SaveCheckpoint(const TrainingLoop& loop, int64_t step, const std::mt19937_64& rng, const Losses& losses,
                            std::string* checkpoint) {
  const std::string name = CheckpointName(step);
  STAGE_RETURN_IF_ERROR(loop.save(loop.dir + "/" + name));
  STAGE_RETURN_IF_ERROR(WriteLosses(loop.dir, losses, loop.loss_names));
  std::ostringstream state;
  state << rng;
  const nlohmann::json j = {{"step", step}, {"checkpoint", name}, {"rng", state.str()}, {"options", loop.options}};
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(loop.dir + "/trainer.json", j.dump(2) + "\n"));
  if (!checkpoint->empty() && *checkpoint != name) {
    std::error_code ec;
    fs::remove(loop.dir + "/" + *checkpoint, ec);
  }
  *checkpoint = name;
  return absl::OkStatus();
}

struct TrainerState {
  int64_t step = 0;
  std::string checkpoint;
  std::mt19937_64 rng;
};

// trainer.json read back and checked against the loop's options (FailedPrecondition names an option the run was
// trained with otherwise).
absl::StatusOr<TrainerState> ReadTrainerState(const std::string& path, const TrainingLoop& loop) {
  std::ifstream in(path);
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, false);
  if (!j.is_object() || !j.contains("step") || !j["step"].is_number_integer() || !j.contains("rng") ||
      !j["rng"].is_string() || !j.contains("checkpoint") || !j["checkpoint"].is_string() || !j.contains("options") ||
      !j["options"].is_object()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a training run's state"));
  }
  for (const auto& [key, value] : loop.options.items()) {
    if (!j["options"].contains(key) || j["options"][key] != value) {
      return absl::FailedPreconditionError(absl::StrCat(path, ": the checkpoint was trained with ", key, " = ",
                                                        j["options"].value(key, nlohmann::json()).dump(), ", not ",
                                                        value.dump()));
    }
  }
  TrainerState t;
  t.step = j["step"].get<int64_t>();
  t.checkpoint = j["checkpoint"].get<std::string>();
  std::istringstream state(j["rng"].get<std::string>());
  state >> t.rng;
  if (state.fail() || t.step < 0 || t.step > loop.schedule.iterations) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": its step or generator state does not read"));
  }
  return t;
}

}  // namespace

float Normal(std::mt19937_64& rng) {
  const double u1 = (static_cast<double>(rng() >> 11) + 0.5) * 0x1.0p-53,
               u2 = static_cast<double>(rng() >> 11) * 0x1.0p-53;
  return static_cast<float>(std::sqrt(-2 * std::log(u1)) * std::cos(2 * kPi * u2));
}

double Uniform(std::mt19937_64& rng, double half_range) {
  return half_range * (2 * static_cast<double>(rng() >> 11) * 0x1.0p-53 - 1);
}

absl::StatusOr<TrainingOutcome> RunTraining(const TrainingLoop& loop) {
  const TrainingSchedule& schedule = loop.schedule;
  std::error_code ec;
  fs::create_directories(loop.dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(loop.dir, ": ", ec.message()));
  TrainingOutcome out;
  std::mt19937_64 rng(loop.seed ^ 0xa55e7ull);
  const std::string trainer = loop.dir + "/trainer.json";
  std::string checkpoint;
  if (schedule.resume && fs::exists(trainer)) {
    absl::StatusOr<TrainerState> state = ReadTrainerState(trainer, loop);
    if (absl::IsFailedPrecondition(state.status()) && schedule.restart_if_different) {
      Logger("processing.asset")->info("{} (starting anew)", state.status().message());
    } else if (!state.ok()) {
      return absl::Status(state.status().code(), absl::StrCat(state.status().message(),
                                                              " (start anew: without resuming, or another directory)"));
    } else {
      STAGE_RETURN_IF_ERROR(loop.load(loop.dir + "/" + state->checkpoint));
      rng = state->rng;
      checkpoint = state->checkpoint;
      out.resumed_from = state->step;
      STAGE_ASSIGN_OR_RETURN(out.losses, ReadLosses(loop.dir + "/loss.csv", out.resumed_from, loop.loss_names));
    }
  }
  const int64_t slow_from = static_cast<int64_t>(0.7 * static_cast<double>(schedule.iterations));
  for (int64_t step = out.resumed_from; step < schedule.iterations; ++step) {
    STAGE_ASSIGN_OR_RETURN(std::vector<double> losses,
                           loop.step(rng, step < slow_from ? schedule.learning_rate : schedule.learning_rate / 5));
    if (losses.size() != loop.loss_names.size()) {
      return absl::InternalError(
          absl::StrCat(loop.what, ": a step gave ", losses.size(), " losses, not ", loop.loss_names.size()));
    }
    out.losses.push_back(std::move(losses));
    if ((step + 1) % schedule.checkpoint_every == 0 || step + 1 == schedule.iterations) {
      STAGE_RETURN_IF_ERROR(SaveCheckpoint(loop, step + 1, rng, out.losses, &checkpoint));
    }
    if (loop.progress && !loop.progress(step + 1, schedule.iterations, out.losses.back())) {
      return absl::CancelledError(absl::StrCat(loop.what, " training stopped at step ", step + 1,
                                               " (checkpoint: ", loop.dir, "/", checkpoint, ")"));
    }
  }
  return out;
}

}  // namespace stage::processing::internal
