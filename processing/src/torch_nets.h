// The torch library (libstage_torch_nets.so, loaded on first use) and what the rest of processing sees of it, without
// torch's headers.
//
// Loading libtorch costs a process about 0.9 s of CPU (its symbols' relocations and its operators' registration), and
// most processes of the stage never train or run a net: every `stage-process` command, a graph's tasks and the
// processing worker of every simulated stage. So the nets (asset_net.cc, warp_net.cc) live in a module of their own
// that LoadTorchNets() opens the first time a net is made; the public classes (asset_net.h, warp_net.h) forward to the
// interfaces below, which the module implements.
#pragma once

#include <sched.h>

#include <algorithm>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "stage/processing/asset_net.h"
#include "stage/processing/warp_net.h"

namespace stage::processing::internal {

// The convolutional trunks' shape: input size, levels, channels at full resolution doubling to a cap.
struct ConvShape {
  int input_size, levels, base_channels, max_channels;
  int Channels(int level) const { return std::min(max_channels, base_channels << std::min(level, 20)); }
  int side() const { return input_size >> levels; }  // of the coarsest level
};

template <typename Options>
ConvShape ShapeOf(const Options& o) {
  return {o.input_size, o.levels, o.base_channels, o.max_channels};
}

// The trunks' shape within the ranges the options' comments give; `bad` names the net.
template <typename Bad>
absl::Status ValidateShape(const ConvShape& shape, Bad bad) {
  if (shape.levels < 2 || shape.levels > 7) return bad(absl::StrCat("levels ", shape.levels, " is not in 2..7"));
  if (shape.input_size < 32 || shape.input_size > 512 || shape.input_size % (1 << shape.levels) != 0) {
    return bad(absl::StrCat("input size ", shape.input_size, " is not in 32..512 and divisible by 2^", shape.levels));
  }
  if (shape.base_channels < 4 || shape.base_channels > 256 || shape.max_channels < shape.base_channels ||
      shape.max_channels > 256) {
    return bad(
        absl::StrCat("channels ", shape.base_channels, " to ", shape.max_channels, " are not within 4..256, rising"));
  }
  return absl::OkStatus();
}

// The threads `threads` stands for: itself, or for 0 the cores this process may run on (its affinity: a cgroup's or
// taskset's cpuset).
inline int ThreadCount(int threads) {
  if (threads > 0) return threads;
  cpu_set_t set;
  const int n = sched_getaffinity(0, sizeof(set), &set) == 0 ? CPU_COUNT(&set)
                                                             : static_cast<int>(std::thread::hardware_concurrency());
  return std::max(1, n);
}

// The nets as the module implements them: the public classes' methods, one for one (their comments are there). The
// module's factories are called with options already validated.
class GeometryVaeNet {
 public:
  virtual ~GeometryVaeNet() = default;
  virtual absl::StatusOr<GeometryLosses> TrainStep(const GeometryBatch& batch, double learning_rate) = 0;
  virtual absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& maps, const std::vector<float>& valid,
                                                    int batch) const = 0;
  virtual absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& geometry_latents, int batch) const = 0;
  virtual absl::StatusOr<std::vector<float>> Reposed(const std::vector<float>& maps, const std::vector<float>& valid,
                                                     int batch) const = 0;
  virtual absl::Status Save(const std::string& path) const = 0;
  virtual absl::Status Load(const std::string& path) = 0;
  virtual absl::Status ExportTorchScript(const std::string& path) const = 0;
  virtual const GeometryVaeOptions& options() const = 0;
  virtual int64_t parameter_count() const = 0;
};

class TextureVaeNet {
 public:
  virtual ~TextureVaeNet() = default;
  virtual absl::StatusOr<TextureLosses> TrainStep(const TextureBatch& batch, double learning_rate) = 0;
  virtual absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& textures, const std::vector<float>& valid,
                                                    int batch) const = 0;
  virtual absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& latents, int batch) const = 0;
  virtual absl::Status Save(const std::string& path) const = 0;
  virtual absl::Status Load(const std::string& path) = 0;
  virtual absl::Status ExportTorchScript(const std::string& path) const = 0;
  virtual const TextureVaeOptions& options() const = 0;
  virtual int64_t parameter_count() const = 0;
};

class ExpressionVaeNet {
 public:
  virtual ~ExpressionVaeNet() = default;
  virtual absl::StatusOr<ExpressionLosses> TrainStep(const ExpressionBatch& batch, double learning_rate) = 0;
  virtual absl::StatusOr<std::vector<float>> Encode(const std::vector<float>& images, int batch) const = 0;
  virtual absl::StatusOr<std::vector<float>> Decode(const std::vector<float>& latents, int batch) const = 0;
  virtual absl::Status Save(const std::string& path) const = 0;
  virtual absl::Status Load(const std::string& path) = 0;
  virtual const ExpressionVaeOptions& options() const = 0;
  virtual int64_t parameter_count() const = 0;
};

class LatentMappingNet {
 public:
  virtual ~LatentMappingNet() = default;
  virtual absl::StatusOr<double> TrainStep(const std::vector<float>& inputs, const std::vector<float>& targets,
                                           const std::vector<float>& noise, int batch, double learning_rate) = 0;
  virtual absl::StatusOr<std::vector<float>> Map(const std::vector<float>& inputs, int batch) const = 0;
  virtual absl::Status Save(const std::string& path) const = 0;
  virtual absl::Status Load(const std::string& path) = 0;
  virtual const LatentMappingOptions& options() const = 0;
  virtual int64_t parameter_count() const = 0;
};

class DrivingNetNet {
 public:
  virtual ~DrivingNetNet() = default;
  virtual absl::StatusOr<double> TrainStep(const std::vector<float>& images, const std::vector<float>& targets,
                                           int batch, double learning_rate) = 0;
  // `geometry` is the module's own (every net is).
  virtual absl::Status UseMapLoss(const GeometryVaeNet& geometry, const std::vector<float>& weights) = 0;
  virtual absl::StatusOr<std::vector<float>> Drive(const std::vector<float>& images, int batch) const = 0;
  virtual absl::Status Save(const std::string& path) const = 0;
  virtual absl::Status Load(const std::string& path) = 0;
  virtual const DrivingNetOptions& options() const = 0;
  virtual int input_size() const = 0;
  virtual int output() const = 0;
  virtual int64_t trained_parameters() const = 0;
};

class WarpNetNet {
 public:
  virtual ~WarpNetNet() = default;
  virtual absl::Status Train(const Image& reference, const std::vector<Image>& frames, const std::vector<Image>& bases,
                             const std::function<bool(int step, double loss)>& step) = 0;
  virtual absl::StatusOr<WarpNetPrediction> Predict(const Image& reference, const Image& frame,
                                                    const Image& base) const = 0;
  virtual const std::vector<double>& losses() const = 0;
};

// What the module gives: its factories and torch's process-wide settings. The module and the programs are built from
// the same sources; `abi` tells a module left from another build.
inline constexpr int kTorchNetsAbi = 1;
struct TorchNets {
  int abi = 0;
  absl::StatusOr<std::unique_ptr<GeometryVaeNet>> (*geometry_vae)(const GeometryVaeOptions& options,
                                                                  const std::vector<float>& mean, float scale);
  absl::StatusOr<std::unique_ptr<TextureVaeNet>> (*texture_vae)(const TextureVaeOptions& options,
                                                                const std::vector<float>& neutral,
                                                                const std::vector<float>& scale);
  absl::StatusOr<std::unique_ptr<ExpressionVaeNet>> (*expression_vae)(const ExpressionVaeOptions& options);
  absl::StatusOr<std::unique_ptr<LatentMappingNet>> (*latent_mapping)(const LatentMappingOptions& options,
                                                                      const std::vector<float>& target_mean,
                                                                      const std::vector<float>& target_scale);
  absl::StatusOr<std::unique_ptr<DrivingNetNet>> (*driving_net)(const ExpressionVaeNet& expression,
                                                                const LatentMappingNet& mapping,
                                                                const DrivingNetOptions& options);
  absl::StatusOr<std::unique_ptr<WarpNetNet>> (*warp_net)(const WarpNetOptions& options);
  int (*set_threads)(int threads);  // SetTorchThreads
  std::string (*blas_library)();    // TorchBlasLibrary
  absl::StatusOr<double> (*conv_floor)(int size, int channels, int batch, int steps, int threads);
};

// What the programs give the module: where its warnings go (the programs' loggers).
struct TorchHost {
  void (*warn)(const std::string& message);
};

// The module's entry point (extern "C", the one symbol it exports).
using TorchNetsEntry = const TorchNets* (*)(const TorchHost* host);
inline constexpr const char* kTorchNetsEntry = "StageTorchNets";
inline constexpr const char* kTorchNetsTarget = "stage_torch_nets";

// The module, opened once per process (thread-safe): from lib/ beside the program's directory (build/bin and
// build/tests share build/lib), or from $FASTAGE_TORCH_NETS where set. FailedPrecondition naming the file when it is
// missing or cannot be opened (dlopen's words), or comes from another build.
absl::StatusOr<const TorchNets*> LoadTorchNets();

}  // namespace stage::processing::internal
