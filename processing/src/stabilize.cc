// Temporal stabilization of fused UV textures, the optical-flow baseline (docs/assets.md#temporal-stabilization).
#include "stage/processing/stabilize.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/photometric_stage.h"
#include "statistics.h"

namespace stage::processing {
namespace {

float Luminance(const float* rgb) { return 0.2126f * rgb[0] + 0.7152f * rgb[1] + 0.0722f * rgb[2]; }

// The albedo's luminance as DIS takes it: 8 bits, gamma 1/2.2, `white` (linear) at 255; 0 where not covered.
cv::Mat Gray(const FusedTextures& t, float white) {
  cv::Mat gray(t.size, t.size, CV_8U, cv::Scalar(0));
  for (size_t i = 0; i < t.state.size(); ++i) {
    if (t.state[i] == TexelState::kEmpty) continue;
    const float l = std::max(0.0f, Luminance(&t.albedo.pixels[3 * i])) / white;
    gray.data[i] = static_cast<uint8_t>(std::clamp(255.0f * std::pow(l, 1 / 2.2f), 0.0f, 255.0f));
  }
  return gray;
}

// `image` sampled at `map` (absolute texel positions, CV_32FC2) bilinearly, where `use` holds; its own value elsewhere.
// Unit vectors are renormalized.
Image Warp(const Image& image, const cv::Mat& map, const std::vector<uint8_t>& use, bool unit) {
  if (image.width == 0) return image;
  Image out = image;
  const cv::Mat in(image.height, image.width, CV_32FC(image.channels), const_cast<float*>(image.pixels.data()));
  cv::Mat warped;
  cv::remap(in, warped, map, cv::noArray(), cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  const auto c = static_cast<size_t>(image.channels);
  const float* w = reinterpret_cast<const float*>(warped.data);
  for (size_t i = 0; i < use.size(); ++i) {
    if (!use[i]) continue;
    float* o = &out.pixels[i * c];
    std::copy_n(&w[i * c], c, o);
    if (unit) {
      const float n = std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
      for (size_t k = 0; k < 3; ++k) o[k] = n > 0 ? o[k] / n : 0.0f;
    }
  }
  return out;
}

}  // namespace

absl::Status StabilizeOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("stabilize: ", what)); };
  if (patch_size < 4 || patch_size > 64) return bad(absl::StrCat("patch_size ", patch_size, " is not in 4..64"));
  if (patch_stride < 1 || patch_stride > patch_size) {
    return bad(absl::StrCat("patch_stride ", patch_stride, " is not in 1..patch_size (", patch_size, ")"));
  }
  if (refinement_iterations < 0 || refinement_iterations > 100) {
    return bad(absl::StrCat("refinement_iterations ", refinement_iterations, " is not in 0..100"));
  }
  if (!(max_flow_px > 0)) return bad(absl::StrCat("max_flow_px ", max_flow_px, " is not above 0"));
  return absl::OkStatus();
}

absl::StatusOr<StabilizedTextures> StabilizeTextures(const FusedTextures& reference, const FusedTextures& frame,
                                                     const StabilizeOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  const int size = reference.size;
  const size_t n = static_cast<size_t>(size) * size;
  if (frame.size != size || reference.state.size() != n || frame.state.size() != n) {
    return absl::InvalidArgumentError(
        absl::StrCat("stabilize: textures of ", frame.size, " texels across against a reference of ", size));
  }
  // Both frames' luminance on the reference's scale: its 99th percentile at white.
  std::vector<float> lum;
  for (size_t i = 0; i < n; ++i) {
    if (reference.state[i] == TexelState::kCovered) lum.push_back(Luminance(&reference.albedo.pixels[3 * i]));
  }
  const float white = lum.empty() ? 1.0f : std::max(1e-6f, static_cast<float>(Quantile(lum, 99, 100)));
  cv::Ptr<cv::DISOpticalFlow> dis = cv::DISOpticalFlow::create(cv::DISOpticalFlow::PRESET_MEDIUM);
  dis->setPatchSize(options.patch_size);
  dis->setPatchStride(options.patch_stride);
  dis->setVariationalRefinementIterations(options.refinement_iterations);
  cv::Mat flow;
  dis->calc(Gray(reference, white), Gray(frame, white), flow);

  StabilizedTextures out;
  out.flow = Image(size, size, 2);
  cv::Mat map(size, size, CV_32FC2);
  std::vector<uint8_t> use(n, 0);
  double flow_sum = 0;
  int64_t flow_count = 0;
  const float max2 = static_cast<float>(options.max_flow_px * options.max_flow_px);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const size_t i = static_cast<size_t>(y) * size + x;
      const cv::Vec2f f = flow.at<cv::Vec2f>(y, x);
      out.flow.pixels[2 * i] = f[0];
      out.flow.pixels[2 * i + 1] = f[1];
      map.at<cv::Vec2f>(y, x) = cv::Vec2f(static_cast<float>(x) + f[0], static_cast<float>(y) + f[1]);
      const int sx = static_cast<int>(std::lround(x + f[0])), sy = static_cast<int>(std::lround(y + f[1]));
      const bool inside = sx >= 0 && sy >= 0 && sx < size && sy < size;
      use[i] = reference.state[i] != TexelState::kEmpty && inside && f[0] * f[0] + f[1] * f[1] <= max2 &&
               frame.state[static_cast<size_t>(sy) * size + sx] != TexelState::kEmpty;
      if (use[i] && reference.state[i] == TexelState::kCovered) {
        flow_sum += std::sqrt(f[0] * f[0] + f[1] * f[1]);
        ++flow_count;
      }
    }
  }
  out.mean_flow_px = flow_count > 0 ? flow_sum / static_cast<double>(flow_count) : 0;
  FusedTextures& t = out.textures;
  t = frame;
  t.albedo = Warp(frame.albedo, map, use, false);
  t.specular = Warp(frame.specular, map, use, false);
  t.roughness = Warp(frame.roughness, map, use, false);
  t.normal_object = Warp(frame.normal_object, map, use, true);
  t.normal_tangent = Warp(frame.normal_tangent, map, use, true);
  t.specular_normal_object = Warp(frame.specular_normal_object, map, use, true);
  t.specular_normal_tangent = Warp(frame.specular_normal_tangent, map, use, true);
  t.weight = Warp(frame.weight, map, use, false);
  t.specular_weight = Warp(frame.specular_weight, map, use, false);
  // The texel states and view counts come from the nearest source texel.
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const size_t i = static_cast<size_t>(y) * size + x;
      if (!use[i]) continue;
      const cv::Vec2f m = map.at<cv::Vec2f>(y, x);
      const size_t s = static_cast<size_t>(std::lround(m[1])) * size + static_cast<size_t>(std::lround(m[0]));
      t.state[i] = frame.state[s];
      if (!frame.views.empty()) t.views[i] = frame.views[s];
    }
  }
  return out;
}

double AlbedoJitter(const FusedTextures& a, const FusedTextures& b, const std::vector<bool>* mask) {
  double sum = 0;
  int64_t count = 0;
  for (size_t i = 0; i < a.state.size() && i < b.state.size(); ++i) {
    if (a.state[i] != TexelState::kCovered || b.state[i] != TexelState::kCovered) continue;
    if (mask != nullptr && !(*mask)[i]) continue;
    const float la = Luminance(&a.albedo.pixels[3 * i]), lb = Luminance(&b.albedo.pixels[3 * i]);
    if (la + lb <= 0) continue;
    sum += std::abs(la - lb) / ((la + lb) / 2);
    ++count;
  }
  return count > 0 ? sum / static_cast<double>(count) : 0;
}

namespace {

std::string FrameMetrics(int64_t frame, int64_t reference, double mean_flow, double jitter_fused,
                         double jitter_stable) {
  nlohmann::ordered_json j;
  j["frame"] = frame;
  j["reference_frame"] = reference;
  j["mean_flow_texels"] = mean_flow;
  // To the frame before (none for the reference): the albedo's jitter as fused and as stabilized.
  j["albedo_jitter_fused"] = jitter_fused;
  j["albedo_jitter_stabilized"] = jitter_stable;
  return j.dump(2);
}

std::string StabilizeRunJson(const StabilizeJob& job, int64_t last) {
  nlohmann::ordered_json run;
  run["stage"] = "stabilize";
  run["take"] = std::filesystem::path(job.take_dir).filename().string();
  run["frames"] = {job.first_frame, last};
  run["reference_frame"] = job.first_frame;
  run["textures"] = job.textures_dir.empty() ? "derived/textures" : job.textures_dir;
  run["method"] = "optical flow (OpenCV DIS) on the albedo in UV";
  run["options"] = {{"patch_size", job.options.patch_size},
                    {"patch_stride", job.options.patch_stride},
                    {"refinement_iterations", job.options.refinement_iterations},
                    {"max_flow_px", job.options.max_flow_px}};
  return run.dump(2) + "\n";
}

}  // namespace

absl::Status StabilizeJob::Validate() const {
  if (take_dir.empty()) return absl::InvalidArgumentError("stabilize: no take directory");
  if (first_frame < 0 || (last_frame >= 0 && last_frame <= first_frame)) {
    return absl::InvalidArgumentError(
        absl::StrCat("stabilize: the frames [", first_frame, ", ", last_frame, ") hold none"));
  }
  return options.Validate();
}

absl::StatusOr<JobResult> RunStabilize(const StabilizeJob& job, const std::function<void(const JobProgress&)>& progress,
                                       const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(job.Validate());
  const std::string textures = PathInTake(job.take_dir, job.textures_dir, "derived/textures");
  const int64_t last = job.last_frame >= 0 ? job.last_frame : EndOfFrames(textures, "albedo.exr", job.first_frame);
  if (last <= job.first_frame) {
    return absl::NotFoundError(
        absl::StrCat(textures, ": no textures from frame ", job.first_frame, " (run the textures stage first)"));
  }
  JobResult result;
  result.output_dir = PathInTake(job.take_dir, job.output_dir, "derived/textures-stable");
  JobProgress p{0, last - job.first_frame,
                absl::StrCat("stabilization: ", last - job.first_frame, " frame(s) onto frame ", job.first_frame)};
  if (progress) progress(p);
  STAGE_ASSIGN_OR_RETURN(const FusedTextures reference, ReadFusedTextures(FrameDir(textures, job.first_frame)));
  FusedTextures previous_fused = reference, previous_stable = reference;
  for (int64_t frame = job.first_frame; frame < last; ++frame) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(
          absl::StrCat("stabilization of ", job.take_dir, " cancelled after ", result.units, " frame(s)"));
    }
    FusedTextures fused = reference;
    StabilizedTextures stable{reference, Image(), 0};
    if (frame != job.first_frame) {
      STAGE_ASSIGN_OR_RETURN(fused, ReadFusedTextures(FrameDir(textures, frame)));
      auto s = StabilizeTextures(reference, fused, job.options);
      if (!s.ok())
        return absl::Status(s.status().code(), absl::StrCat(FrameDir(textures, frame), ": ", s.status().message()));
      stable = *std::move(s);
    }
    const double jitter_fused = AlbedoJitter(previous_fused, fused),
                 jitter_stable = AlbedoJitter(previous_stable, stable.textures);
    STAGE_RETURN_IF_ERROR(
        WriteFusedTextures(FrameDir(result.output_dir, frame), stable.textures,
                           FrameMetrics(frame, job.first_frame, stable.mean_flow_px, jitter_fused, jitter_stable),
                           absl::StrFormat("frame %d stabilized onto frame %d", frame, job.first_frame)));
    previous_fused = std::move(fused);
    previous_stable = std::move(stable.textures);
    ++result.units;
    p.done = result.units;
    p.message = absl::StrFormat("frame %d: flow %.2f texels, albedo jitter %.2f %% (fused %.2f %%)", frame,
                                stable.mean_flow_px, 100 * jitter_stable, 100 * jitter_fused);
    if (progress) progress(p);
  }
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/run.json", StabilizeRunJson(job, last)));
  return result;
}

}  // namespace stage::processing
