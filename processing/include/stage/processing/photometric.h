// Photometric stereo under spherical gradient illumination (docs/processing.md): from the 38 pattern images of one
// cycle of a high-speed camera, the diffuse normal and albedo of every pixel, with a confidence.
//
// Diffuse: cross-polarized images hold diffuse reflection only (and the analyzer's small leak of specular, removed
// with the parallel twin). Under pattern p a Lambertian pixel reads white_scale * albedo * n . H_p(n) (light_model.h),
// linear in u = albedo * n once the units lit on n's side are known: u is solved per pixel by least squares over all
// 19 cross patterns, each weighted by the inverse of its noise variance (shot and read noise at the predicted
// level), and re-solved with the lit set of the new normal.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/light_model.h"

namespace stage::processing {

// A float image, channels interleaved.
struct Image {
  int width = 0;
  int height = 0;
  int channels = 1;
  std::vector<float> pixels;

  Image() = default;
  Image(int w, int h, int c) : width(w), height(h), channels(c), pixels(static_cast<size_t>(w) * h * c, 0.f) {}
  float* at(int x, int y) { return &pixels[(static_cast<size_t>(y) * width + x) * channels]; }
  const float* at(int x, int y) const { return &pixels[(static_cast<size_t>(y) * width + x) * channels]; }
};

// What the solver needs to know of the camera, at the images' size.
struct PhotometricCamera {
  // OpenCV convention: camera = world_to_camera * (world - position_mm); x right, y down, z forward.
  Eigen::Matrix3d world_to_camera = Eigen::Matrix3d::Identity();
  Eigen::Vector3d position_mm = Eigen::Vector3d(0, 0, 1000);
  // DN above black that a white Lambertian surface (albedo 1) gives per unit of n . H_p(n).
  double white_scale = 1;
  // Electrons per DN, read noise (electrons), and the level (DN above black) at which a pixel is saturated.
  double gain_e_per_dn = 1;
  double read_noise_e = 5;
  double saturation_dn = 1e30;
  // The fraction of specular light the cross analyzer lets through.
  double cross_leak = 0;
};

struct PhotometricOptions {
  // Re-solves with the lit set of the last normal.
  int iterations = 3;
  // Octahedral table of H_p(n): cells per side.
  int table_size = 128;
  // Below this full-on level (DN above black, sum of channels) a pixel is not solved (background, deep shadow).
  double min_signal_dn = 4;
};

// Confidence flags, per pixel.
enum PhotometricFlag : uint8_t {
  kSaturated = 1,  // some pattern image clipped
  kLowSignal = 2,  // too dark to solve (below min_signal_dn), or shadowed from most of the dome
  kBadFit = 4,     // the patterns disagree with a Lambertian surface (mislabeled or blended patterns, occlusion)
};

struct PhotometricMaps {
  int width = 0, height = 0;
  Image diffuse_normal_world;   // 3 channels, unit vectors, stage frame; 0 where not solved
  Image diffuse_normal_camera;  // the same in the camera frame
  Image albedo;                 // 3 channels, linear RGB (the images' channel order)
  Image confidence;             // 1 channel, 0..1
  Image fit_residual;           // 1 channel: the weighted fit's reduced chi-square (about 1 for a good fit)
  std::vector<uint8_t> flags;   // PhotometricFlag bits
};

// `frames`: the cycle's images in pattern order (light.patterns), demosaiced RGB, DN above black. InvalidArgument
// names a missing pattern or a size mismatch.
// `positions` (optional): each pixel's surface point, stage frame, mm (3 channels; from geometry): the units' real
// directions and distances are then used there (slow: every unit, every pattern, every pixel).
absl::StatusOr<PhotometricMaps> SolvePhotometric(const LightModel& light, const std::vector<Image>& frames,
                                                 const PhotometricCamera& camera,
                                                 const PhotometricOptions& options = {},
                                                 const Image* positions = nullptr);

// Angle between two unit vectors, degrees.
double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b);

}  // namespace stage::processing
