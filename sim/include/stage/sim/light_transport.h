// Light transport of the simulated stage, computed the way the physics allows: for one subject pose and one camera,
// every pixel's response to every LED unit at full drive is computed once (diffuse and specular, with visibility);
// any exposure is then a matrix product of those responses with the units' emitter levels averaged over the
// exposure, so a pattern image costs two dot products per pixel and a mistimed exposure blends two patterns exactly.
//
// Polarization: emitters sit behind linear polarizers, cameras behind analyzers. Diffuse reflection depolarizes, so
// half of it passes the analyzer whichever the emitter; specular reflection keeps the polarization, so it passes
// fully from parallel emitters and only as `leakage` from cross ones.
//   radiance = 1/2 albedo * sum_l (cross_l + parallel_l) D_l + sum_l (parallel_l + leakage cross_l) S_l
// with D_l = V max(0, n.w) I / (pi d^2) and S_l = V rho_s D_ggx(h) G(w, v) I / (4 (n.v) d^2).
#pragma once

#include <Eigen/Core>
#include <atomic>
#include <cstdint>
#include <map>
#include <memory>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_model.h"
#include "stage/common/ggx.h"
#include "stage/sim/dome.h"
#include "stage/sim/subject.h"

namespace stage::sim {

using RowMatrixXf = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Emitter levels of every unit averaged over an exposure, in [0, 1] of full drive.
struct EmitterLevels {
  Eigen::VectorXf cross;
  Eigen::VectorXf parallel;
};

// The few exposures a renderer will be asked for (a take of the full-on patterns only), for responses computed for
// them alone: a pixel's diffuse and specular sums under each exposure instead of its response to every unit. The
// arithmetic is the same; what goes is the hits x units matrices (3.9 GB for a 12-megapixel view of the head) and the
// writing of them, most of a board's render at full scale.
struct ExposureBasis {
  std::vector<EmitterLevels> levels;
  // The crossed polarizers' leakage the specular sums are made with (the camera's, CrossLeakage).
  float leakage = 0;
  // The index of the exposure equal to `l` under `leakage_of_camera` (to the bit), -1 if none.
  int Find(const EmitterLevels& l, float leakage_of_camera) const;
};

// Supersampled (n x n rays a pixel), a pixel's rows average its rays' (a ray that misses adds nothing, so an edge pixel
// is partly covered) and its albedo averages the albedo its rays hit: the product of the averages stands for the
// average of the products, which holds where the lighting is even across the pixel.
struct PixelResponses {
  int width = 0;
  int height = 0;
  // Row-major index of every pixel that sees the subject, and what it sees there (its first ray that hits).
  std::vector<int32_t> pixels;
  std::vector<Eigen::Vector3f> albedo;
  std::vector<Hit> hits;
  // hits x units: D and S above, per unit of emitter drive. Where `basis` is set, hits x its exposures instead: each
  // exposure's sum_l (cross_l + parallel_l) D_l and sum_l (parallel_l + leakage cross_l) S_l.
  RowMatrixXf diffuse;
  RowMatrixXf specular;
  std::shared_ptr<const ExposureBasis> basis;
};

// How far a long computation has got, for a reader on another thread: units of work done (rays traced, pixels lit) of
// about `total` (refined as the work learns its size).
struct WorkProgress {
  std::atomic<uint64_t> done{0};
  std::atomic<uint64_t> total{0};
};

// A camera's pixel rays (CameraModel::PixelRays) for each sub-pixel offset asked for, undistorted once and kept while
// they fit in `budget_bytes`: OpenCV's iterative undistortion of every pixel was a quarter of a camera node's time when
// a moving subject had it redone every frame. Not thread-safe: one per camera, used by one thread at a time.
class CameraRays {
 public:
  explicit CameraRays(const CameraModel& camera, size_t budget_bytes = size_t{256} << 20)
      : camera_(camera), budget_bytes_(budget_bytes) {}
  const CameraModel& camera() const { return camera_; }
  // Rays through (x + dx, y + dy), row-major, unit length, stage frame.
  std::shared_ptr<const std::vector<Eigen::Vector3f>> At(double dx, double dy);

 private:
  CameraModel camera_;
  size_t budget_bytes_;
  size_t kept_bytes_ = 0;
  std::map<std::pair<double, double>, std::shared_ptr<const std::vector<Eigen::Vector3f>>> kept_;
};

// What every pixel's ray meets (row-major; hit == false where it misses the subject); rays through (x + dx, y + dy).
// Each ray traced adds one to `progress->done` where given.
std::vector<Hit> TracePixels(CameraRays& rays, const Subject& subject, int threads = 0, double dx = 0, double dy = 0,
                             WorkProgress* progress = nullptr);
std::vector<Hit> TracePixels(const CameraModel& camera, const Subject& subject, int threads = 0, double dx = 0,
                             double dy = 0, WorkProgress* progress = nullptr);

// Every pixel's albedo averaged over the n x n rays through it that meet the subject (row-major), and how many did
// (0: none; its albedo is then zero). With `only`, those pixels' (distinct row-major indices) alone; the others count
// none.
struct AreaAlbedo {
  std::vector<Eigen::Vector3f> albedo;
  std::vector<int> rays;
};
AreaAlbedo TraceAreaAlbedo(CameraRays& rays, const Subject& subject, int n, int threads = 0,
                           WorkProgress* progress = nullptr, const std::vector<int32_t>* only = nullptr);
AreaAlbedo TraceAreaAlbedo(const CameraModel& camera, const Subject& subject, int n, int threads = 0,
                           WorkProgress* progress = nullptr);

// Camera direction -> pixel responses, on `threads` threads (0: one per core), with `supersample` x `supersample`
// rays a pixel (1: through its centre). With `texture_samples` > `supersample` a pixel's albedo is the average of
// texture_samples x texture_samples rays' (TraceAreaAlbedo) instead of its lighting rays'. With `basis`, the responses
// are each exposure's sums (PixelResponses::basis).
PixelResponses ComputeResponses(CameraRays& rays, const Subject& subject, const Dome& dome, int threads = 0,
                                int supersample = 1, WorkProgress* progress = nullptr, int texture_samples = 0,
                                std::shared_ptr<const ExposureBasis> basis = nullptr);
PixelResponses ComputeResponses(const CameraModel& camera, const Subject& subject, const Dome& dome, int threads = 0,
                                int supersample = 1, WorkProgress* progress = nullptr, int texture_samples = 0,
                                std::shared_ptr<const ExposureBasis> basis = nullptr);

// Linear RGB radiance of one exposure, width x height x 3 floats, row-major; pixels that miss the subject are 0.
// Responses with a basis render only its exposures (under its leakage): InvalidArgument for any other (unless no
// pixel sees the subject: black under any light).
absl::StatusOr<std::vector<float>> RenderRadianceOf(const PixelResponses& responses, const EmitterLevels& levels,
                                                    float leakage);
// The same for responses to every unit (no basis), which render any exposure.
std::vector<float> RenderRadiance(const PixelResponses& responses, const EmitterLevels& levels, float leakage);

// Leakage of crossed polarizers for a camera: leakage + growth * sin^2 of its optical axis' angle from +z.
float CrossLeakage(const CameraModel& camera, double leakage, double growth);

}  // namespace stage::sim
