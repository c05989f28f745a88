// Temporal stabilization of fused UV textures, the optical-flow baseline (docs/assets.md#temporal-stabilization).
#include "stage/processing/stabilize.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/map_files.h"
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

absl::string_view StabilizeMethodName(StabilizeMethod method) {
  switch (method) {
    case StabilizeMethod::kFlow:
      return "flow";
    case StabilizeMethod::kUNet:
      return "unet";
  }
  return "unknown";
}

absl::StatusOr<StabilizeMethod> ParseStabilizeMethod(absl::string_view name) {
  for (StabilizeMethod m : {StabilizeMethod::kFlow, StabilizeMethod::kUNet}) {
    if (name == StabilizeMethodName(m)) return m;
  }
  return absl::InvalidArgumentError(absl::StrCat("stabilize: no method \"", name, "\" (flow, unet)"));
}

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
  if (net_size < 32 || net_size > 4096 || (net_size & (net_size - 1)) != 0) {
    return bad(absl::StrCat("net_size ", net_size, " is not a power of two in 32..4096"));
  }
  STAGE_RETURN_IF_ERROR(net.Validate());
  if (method == StabilizeMethod::kUNet && net_size < (2 << net.levels)) {
    return bad(absl::StrCat("net_size ", net_size, " is below 2^(levels + 1) = ", 2 << net.levels, " for ", net.levels,
                            " levels"));
  }
  return absl::OkStatus();
}

namespace {

absl::Status CheckSizes(const FusedTextures& reference, const FusedTextures& frame) {
  const size_t n = static_cast<size_t>(reference.size) * reference.size;
  if (frame.size != reference.size || reference.state.size() != n || frame.state.size() != n) {
    return absl::InvalidArgumentError(
        absl::StrCat("stabilize: textures of ", frame.size, " texels across against a reference of ", reference.size));
  }
  return absl::OkStatus();
}

// DIS's flow from `reference`'s albedo to `frame`'s: 2 channels, texels.
Image OpticalFlow(const FusedTextures& reference, const FusedTextures& frame, const StabilizeOptions& options) {
  const int size = reference.size;
  const size_t n = static_cast<size_t>(size) * size;
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
  Image out(size, size, 2);
  std::copy_n(reinterpret_cast<const float*>(flow.data), out.pixels.size(), out.pixels.data());
  return out;
}

// `frame`'s textures warped onto `reference`'s texels along `flow` (2 channels, texels, the textures' size).
StabilizedTextures ApplyFlow(const FusedTextures& reference, const FusedTextures& frame, Image flow,
                             double max_flow_px) {
  const int size = reference.size;
  const size_t n = static_cast<size_t>(size) * size;
  StabilizedTextures out;
  out.flow = std::move(flow);
  cv::Mat map(size, size, CV_32FC2);
  std::vector<uint8_t> use(n, 0);
  double flow_sum = 0;
  int64_t flow_count = 0;
  const float max2 = static_cast<float>(max_flow_px * max_flow_px);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const size_t i = static_cast<size_t>(y) * size + x;
      const cv::Vec2f f(out.flow.pixels[2 * i], out.flow.pixels[2 * i + 1]);
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

// The U-Net's input for a frame's textures: their albedo's log-luminance and coverage averaged down to `net_size`
// (a texel of the net is covered when every texel it holds is).
Image NetInput(const FusedTextures& t, int net_size) {
  const int size = t.size;
  cv::Mat value(size, size, CV_32F, cv::Scalar(0)), cover(size, size, CV_32F, cv::Scalar(0));
  for (size_t i = 0; i < t.state.size(); ++i) {
    if (t.state[i] != TexelState::kCovered) continue;
    value.at<float>(static_cast<int>(i)) = std::log(std::max(1e-4f, Luminance(&t.albedo.pixels[3 * i])));
    cover.at<float>(static_cast<int>(i)) = 1;
  }
  if (net_size < size) {
    cv::resize(value, value, cv::Size(net_size, net_size), 0, 0, cv::INTER_AREA);
    cv::resize(cover, cover, cv::Size(net_size, net_size), 0, 0, cv::INTER_AREA);
  }
  const int n = std::min(net_size, size);
  Image out(n, n, 2);
  for (int i = 0; i < n * n; ++i) {
    const float c = cover.at<float>(i);
    out.pixels[2 * i] = c > 0 ? value.at<float>(i) / c : 0.0f;
    out.pixels[2 * i + 1] = c > 0.999f ? 1.0f : 0.0f;
  }
  return out;
}

// `image` (any channels) resized to `size` texels across with `interpolation` (INTER_AREA down, INTER_LINEAR up), its
// values times `gain` (for a warp, the ratio of the sizes: its vectors in the new texels).
Image Resized(const Image& image, int size, float gain, int interpolation) {
  if (image.width == size) return image;
  cv::Mat in(image.height, image.width, CV_32FC(image.channels), const_cast<float*>(image.pixels.data())), out;
  cv::resize(in, out, cv::Size(size, size), 0, 0, interpolation);
  Image resized(size, size, image.channels);
  const float* p = reinterpret_cast<const float*>(out.data);
  for (size_t i = 0; i < resized.pixels.size(); ++i) resized.pixels[i] = gain * p[i];
  return resized;
}

// A warp (2 channels, texels) resized to `size` texels across, its vectors in the new texels.
Image ResizedWarp(const Image& flow, int size, int interpolation) {
  return Resized(flow, size, static_cast<float>(size) / static_cast<float>(flow.width), interpolation);
}

// The flow's stabilization of one frame.
StabilizedTextures FlowStabilized(const FusedTextures& reference, const FusedTextures& frame,
                                  const StabilizeOptions& options) {
  return ApplyFlow(reference, frame, OpticalFlow(reference, frame, options), options.max_flow_px);
}

// The U-Net's stabilization: frames are added (their inputs kept at the net's size), the net trained on them, then
// each frame's textures warped along its prediction.
class NetStabilizer {
 public:
  static absl::StatusOr<NetStabilizer> Create(const FusedTextures& reference, const StabilizeOptions& options) {
    STAGE_ASSIGN_OR_RETURN(std::unique_ptr<WarpNet> net, WarpNet::Create(options.net));
    return NetStabilizer(reference, options, std::move(net));
  }
  // Frame i (in the order added): its input at the net's size and, with net_from_flow, the optical flow's warp there,
  // kept for Apply.
  void Add(const FusedTextures& frame) {
    inputs_.push_back(NetInput(frame, options_.net_size));
    if (options_.net_from_flow) {
      bases_.push_back(ResizedWarp(OpticalFlow(*reference_, frame, options_), reference_input_.width, cv::INTER_AREA));
    }
  }
  absl::Status Train(const std::function<bool(int, double)>& progress) {
    return net_->Train(reference_input_, inputs_, bases_, progress);
  }
  // Frame i's textures (the frame added i-th) warped along the net's prediction.
  absl::StatusOr<StabilizedTextures> Apply(size_t i, const FusedTextures& frame) const {
    STAGE_ASSIGN_OR_RETURN(const WarpNetPrediction p,
                           net_->Predict(reference_input_, inputs_[i], bases_.empty() ? Image() : bases_[i]));
    StabilizedTextures out =
        ApplyFlow(*reference_, frame, ResizedWarp(p.flow, reference_->size, cv::INTER_LINEAR), options_.max_flow_px);
    out.wrinkle = Resized(p.wrinkle, reference_->size, 1.0f, cv::INTER_LINEAR);
    return out;
  }
  const std::vector<double>& losses() const { return net_->losses(); }

 private:
  NetStabilizer(const FusedTextures& reference, const StabilizeOptions& options, std::unique_ptr<WarpNet> net)
      : reference_(&reference),
        options_(options),
        net_(std::move(net)),
        reference_input_(NetInput(reference, options.net_size)) {}
  const FusedTextures* reference_;
  StabilizeOptions options_;
  std::unique_ptr<WarpNet> net_;
  Image reference_input_;
  std::vector<Image> inputs_, bases_;
};

}  // namespace

absl::StatusOr<StabilizedTextures> StabilizeTextures(const FusedTextures& reference, const FusedTextures& frame,
                                                     const StabilizeOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_RETURN_IF_ERROR(CheckSizes(reference, frame));
  return FlowStabilized(reference, frame, options);
}

absl::StatusOr<std::vector<StabilizedTextures>> StabilizeSequence(const FusedTextures& reference,
                                                                  const std::vector<FusedTextures>& frames,
                                                                  const StabilizeOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  for (const FusedTextures& frame : frames) STAGE_RETURN_IF_ERROR(CheckSizes(reference, frame));
  std::vector<StabilizedTextures> out;
  if (options.method == StabilizeMethod::kFlow) {
    for (const FusedTextures& frame : frames) out.push_back(FlowStabilized(reference, frame, options));
    return out;
  }
  STAGE_ASSIGN_OR_RETURN(NetStabilizer net, NetStabilizer::Create(reference, options));
  for (const FusedTextures& frame : frames) net.Add(frame);
  STAGE_RETURN_IF_ERROR(net.Train({}));
  for (size_t i = 0; i < frames.size(); ++i) {
    STAGE_ASSIGN_OR_RETURN(StabilizedTextures s, net.Apply(i, frames[i]));
    out.push_back(std::move(s));
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

std::string StabilizeRunJson(const StabilizeJob& job, int64_t last, const std::vector<double>& losses) {
  nlohmann::ordered_json run;
  run["stage"] = "stabilize";
  run["take"] = std::filesystem::path(job.take_dir).filename().string();
  run["frames"] = {job.first_frame, last};
  run["reference_frame"] = job.first_frame;
  run["textures"] = job.textures_dir.empty() ? "derived/textures" : job.textures_dir;
  const StabilizeOptions& o = job.options;
  run["method"] = StabilizeMethodName(o.method);
  if (o.method == StabilizeMethod::kFlow) {
    run["options"] = {{"patch_size", o.patch_size},
                      {"patch_stride", o.patch_stride},
                      {"refinement_iterations", o.refinement_iterations},
                      {"max_flow_px", o.max_flow_px}};
  } else {
    run["options"] = {{"net_from_flow", o.net_from_flow},
                      {"net_size", o.net_size},
                      {"levels", o.net.levels},
                      {"base_channels", o.net.base_channels},
                      {"iterations", o.net.iterations},
                      {"learning_rate", o.net.learning_rate},
                      {"loss_scales", o.net.loss_scales},
                      {"smoothness", o.net.smoothness},
                      {"wrinkle_sparsity", o.net.wrinkle_sparsity},
                      {"wrinkle_smoothness", o.net.wrinkle_smoothness},
                      {"threads", TorchThreadCount(o.net.threads)},  // the count used: results depend on it
                      {"seed", o.net.seed},
                      {"max_flow_px", o.max_flow_px}};
    if (o.net_from_flow) {
      run["options"]["flow"] = {{"patch_size", o.patch_size},
                                {"patch_stride", o.patch_stride},
                                {"refinement_iterations", o.refinement_iterations}};
    }
    run["final_loss"] = losses.empty() ? 0.0 : losses.back();
  }
  return run.dump(2) + "\n";
}

// The U-Net's losses, one row per training step.
std::string LossCsv(const std::vector<double>& losses) {
  std::string csv = "step,loss\n";
  for (size_t i = 0; i < losses.size(); ++i) absl::StrAppendFormat(&csv, "%d,%.6g\n", i, losses[i]);
  return csv;
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

namespace {

// The U-Net's training for RunStabilize: every frame's albedo read, the net trained; progress every tenth of the steps.
absl::StatusOr<std::optional<NetStabilizer>> TrainForTake(const StabilizeJob& job, const std::string& textures,
                                                          int64_t last, const FusedTextures& reference,
                                                          const std::function<void(const JobProgress&)>& progress,
                                                          const std::function<bool()>& cancelled) {
  if (job.options.method != StabilizeMethod::kUNet) return std::optional<NetStabilizer>();
  STAGE_ASSIGN_OR_RETURN(NetStabilizer net, NetStabilizer::Create(reference, job.options));
  // The reference against itself teaches nothing but the identity: the net trains on the other frames (on the
  // reference only when it is the range's one frame). Frame f is the net's (f - first_frame - 1)-th.
  for (int64_t frame = last > job.first_frame + 1 ? job.first_frame + 1 : job.first_frame; frame < last; ++frame) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(absl::StrCat("stabilization of ", job.take_dir, " cancelled"));
    }
    STAGE_ASSIGN_OR_RETURN(const FusedTextures fused, ReadFusedTextures(FrameDir(textures, frame)));
    net.Add(fused);
  }
  const int steps = job.options.net.iterations;
  JobProgress p{0, last - job.first_frame, ""};
  STAGE_RETURN_IF_ERROR(net.Train([&](int step, double loss) {
    if (progress && ((step + 1) % std::max(1, steps / 10) == 0 || step + 1 == steps)) {
      p.message = absl::StrFormat("U-Net: step %d of %d, loss %.4f", step + 1, steps, loss);
      progress(p);
    }
    return !(cancelled && cancelled());
  }));
  return std::optional<NetStabilizer>(std::move(net));
}

}  // namespace

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
                absl::StrCat("stabilization (", StabilizeMethodName(job.options.method), "): ", last - job.first_frame,
                             " frame(s) onto frame ", job.first_frame)};
  if (progress) progress(p);
  STAGE_ASSIGN_OR_RETURN(const FusedTextures reference, ReadFusedTextures(FrameDir(textures, job.first_frame)));
  STAGE_ASSIGN_OR_RETURN(const std::optional<NetStabilizer> net,
                         TrainForTake(job, textures, last, reference, progress, cancelled));
  FusedTextures previous_fused = reference, previous_stable = reference;
  for (int64_t frame = job.first_frame; frame < last; ++frame) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(
          absl::StrCat("stabilization of ", job.take_dir, " cancelled after ", result.units, " frame(s)"));
    }
    FusedTextures fused = reference;
    StabilizedTextures stable{reference, Image(), 0, Image()};
    if (net) stable.wrinkle = Image(reference.size, reference.size, 1);
    if (frame != job.first_frame) {
      STAGE_ASSIGN_OR_RETURN(fused, ReadFusedTextures(FrameDir(textures, frame)));
      auto s = net ? net->Apply(static_cast<size_t>(frame - job.first_frame - 1), fused)
                   : StabilizeTextures(reference, fused, job.options);
      if (!s.ok())
        return absl::Status(s.status().code(), absl::StrCat(FrameDir(textures, frame), ": ", s.status().message()));
      stable = *std::move(s);
    }
    const double jitter_fused = AlbedoJitter(previous_fused, fused),
                 jitter_stable = AlbedoJitter(previous_stable, stable.textures);
    const std::string out_dir = FrameDir(result.output_dir, frame);
    STAGE_RETURN_IF_ERROR(
        WriteFusedTextures(out_dir, stable.textures,
                           FrameMetrics(frame, job.first_frame, stable.mean_flow_px, jitter_fused, jitter_stable),
                           absl::StrFormat("frame %d stabilized onto frame %d", frame, job.first_frame)));
    if (net) STAGE_RETURN_IF_ERROR(WriteExr(out_dir + "/wrinkle.exr", stable.wrinkle));
    previous_fused = std::move(fused);
    previous_stable = std::move(stable.textures);
    ++result.units;
    p.done = result.units;
    p.message = absl::StrFormat("frame %d: flow %.2f texels, albedo jitter %.2f %% (fused %.2f %%)", frame,
                                stable.mean_flow_px, 100 * jitter_stable, 100 * jitter_fused);
    if (progress) progress(p);
  }
  const std::vector<double> no_losses;
  const std::vector<double>& losses = net ? net->losses() : no_losses;
  if (net) STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/loss.csv", LossCsv(losses)));
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/run.json", StabilizeRunJson(job, last, losses)));
  return result;
}

}  // namespace stage::processing
