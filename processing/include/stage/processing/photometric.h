// Photometric stereo under spherical gradient illumination (docs/processing.md): from the 38 pattern images of one
// cycle of a high-speed camera, per pixel the diffuse normal and albedo, the specular normal, intensity and roughness,
// and a confidence.
//
// Diffuse: cross-polarized images hold diffuse reflection only (and the analyzer's small leak of specular, removed
// with the parallel twin). Under pattern p a Lambertian pixel reads white_scale * albedo * n . H_p(n) (light_model.h),
// linear in u = albedo * n once the units lit on n's side are known: u is solved per pixel by least squares over all
// cross patterns, each weighted by the inverse of its noise variance (shot and read noise at the predicted level),
// and re-solved with the lit set of the new normal.
//
// Specular: parallel minus cross is specular only. Its 19 gradient images are the lobe's moments up to second order
// (Ma et al. 2007; Ghosh et al. 2009): the first-order ones give its direction, the second-order ones its spread.
// Per pixel the normal, roughness (GGX alpha) and intensity are fitted to them by noise-weighted least squares with
// the stage's own units in the model (a dome of 168 point sources is far from a continuous sphere for a lobe a few
// units wide), starting from the lobe's centroid. Specular normals are noisy by nature: their departure from the
// diffuse normal is then filtered adaptively (a local Wiener filter that keeps what stands above each pixel's own
// noise, so pore-scale detail stays where the signal carries it).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/mesh.h"
#include "stage/processing/light_model.h"

namespace stage::processing {

class VisualHull;

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

// The colour filter of a sensor: mono, or a Bayer mosaic with its red site at (red_x, red_y) in the 2 x 2 tile
// (GenICam BayerRG: 0, 0; GR: 1, 0; GB: 0, 1; BG: 1, 1).
struct Mosaic {
  bool mono = false;
  int red_x = 0, red_y = 0;
  // Which colour (0 R, 1 G, 2 B) pixel (x, y) sees; for mono, 1.
  int Color(int x, int y) const {
    if (mono) return 1;
    const bool red_row = ((y ^ red_y) & 1) == 0, red_col = ((x ^ red_x) & 1) == 0;
    return red_row == red_col ? (red_row ? 0 : 2) : 1;
  }
};

// What the solver needs to know of the camera, at the images' size.
struct PhotometricCamera {
  // OpenCV convention: camera = world_to_camera * (world - position_mm); x right, y down, z forward.
  Eigen::Matrix3d world_to_camera = Eigen::Matrix3d::Identity();
  Eigen::Vector3d position_mm = Eigen::Vector3d(0, 0, 1000);
  // The unit ray through every pixel's centre, stage frame, row-major (CameraModel::PixelRays). Empty: every pixel
  // looks from position_mm at the stage origin.
  std::vector<Eigen::Vector3f> rays;
  // DN above black that a white Lambertian surface (albedo 1) gives per unit of n . H_p(n).
  double white_scale = 1;
  // Electrons per DN, read noise (electrons), and the level (DN above black) at which a pixel is saturated.
  double gain_e_per_dn = 1;
  double read_noise_e = 5;
  double saturation_dn = 1e30;
  // The fraction of specular light the cross analyzer lets through.
  double cross_leak = 0;
  // The colour filter SolvePhotometric's images were demosaiced from (DemosaicCycle). With a Bayer mosaic each
  // pixel's albedo is solved in the colour it measures, and the two it does not measure come from its neighbours' hue,
  // as the fast solver has them from the raw mosaic (docs/processing.md). None: every pixel's three channels are
  // measured (RGB images), each solved.
  std::optional<Mosaic> mosaic;
};

// What is known of the surface every pixel sees (from a mesh: multi-view stereo, or the simulator's ground truth):
// where it is, and which units it sees. With it the units' real directions and distances and their shadows enter the
// model; without it every pixel sees every unit from the stage origin.
struct PixelGeometry {
  int width = 0, height = 0;
  int words = 0;                  // 64-bit words of `visible` per pixel
  std::vector<float> points;      // 3 per pixel, stage frame, mm; NaN where the pixel sees no surface
  std::vector<uint64_t> visible;  // per pixel: bit l of the units nothing hides from the point (LightModel::ViewFrom)
  std::vector<uint8_t> placed;    // per pixel: 1 where the point was placed beyond the mesh (FillGeometry, then
                                  // RefillGeometry), not traced into it; empty: none placed
  // Per placed pixel, the stretch of its ray (distance from the camera, mm) inside the frame's visual hull, cut to
  // PhotometricOptions::geometry_hull_depth_mm past its entry, which its point is kept within: [hull_in, hull_out];
  // NaN where the ray missed the hull. Empty: no hull.
  std::vector<float> hull_in, hull_out;

  bool Covers(size_t pixel) const { return points[3 * pixel] == points[3 * pixel]; }
  const uint64_t* Visible(size_t pixel) const { return &visible[pixel * static_cast<size_t>(words)]; }
};

// Traces every pixel's ray (camera.rays) into `mesh`, and from where it lands a shadow ray to every unit; a unit with
// the mesh in between is hidden. The shadow rays start `clearance_mm` from the point, towards their unit: a
// reconstructed mesh is rough at the scale of its error, and its own facets would otherwise shadow the point (which
// units lie below the horizon the solver judges by the normal it solves, not by the mesh's facet). A ray that meets
// the side of the surface fewer rays meet (its inside, whichever way the mesh is wound) came through a hole in it, and
// its pixel is left uncovered. `threads` 0: one per core.
PixelGeometry TraceGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, int width, int height,
                            const LightModel& light, double clearance_mm, int threads = 0);

struct PhotometricOptions {
  // Re-solves of the diffuse normal with the lit set of the last normal.
  int iterations = 3;
  // Octahedral table of H_p(n) (no geometry): cells per side.
  int table_size = 128;
  // Below this full-on level (DN above black, sum of channels) a pixel is not solved (background, deep shadow).
  double min_signal_dn = 4;
  // Nor below this many standard deviations of the read noise of that sum (a dark pixel's noise): noise alone must not
  // pass for the subject (at 5, about one dark pixel in three million does).
  double min_signal_sigma = 5;
  // Below this full-on specular level (parallel - cross, DN summed over channels, in units of its own noise) the
  // specular lobe is not fitted.
  double min_specular_snr = 3;
  // A fitted lobe counts as measured when its normal's standard deviation is below this (degrees) and its intensity's
  // below half the intensity; else the pixel is flagged kNoSpecular (the lobe points off the dome, or is too faint).
  double max_specular_sigma_deg = 15;
  // Above this the albedo a pixel solves to is no surface's: the model is wrong there (a deep cavity, light
  // reflected between surfaces, an occlusion the geometry misses). Such a pixel is flagged kImplausible, its albedo is
  // left out (0), its confidence is 0, and it lends no colour to its neighbours. Default 1.5 (skin reflects below
  // 0.8; the margin is for noise).
  double max_albedo = 1.5;
  // Radius (pixels) of the adaptive filter on the specular normals' departure from the diffuse ones, and on
  // roughness; 0: raw fits.
  int specular_filter_radius = 2;
  // With geometry: shadow rays start this far from the surface point, towards their unit (TraceGeometry), mm.
  // Default 2: a multi-view stereo mesh's roughness (0.1-1 mm) must not shadow its own points; on the simulator's
  // true mesh the maps change by under 0.01 degrees (docs/geometry.md).
  double shadow_clearance_mm = 2;
  // Pixels the geometry's mesh misses within this many pixels of ones it covers are placed at their neighbours'
  // distance (FillGeometry); 0: none. Default 128: with the refill below, no subject pixel of a half-resolution take
  // is left without a point (docs/geometry.md).
  int geometry_fill_px = 128;
  // Then, this many times, the placed pixels are placed again on the surface the solved normals describe
  // (RefillGeometry) and solved again (PhotometricSolver::SolveAgain); 0: they keep their neighbours' distance. Default
  // 1; at most 4.
  int geometry_refill_passes = 1;
  // Where the geometry comes with a visual hull (multi-view stereo's silhouettes), the placed points are kept inside
  // it, at most geometry_hull_depth_mm past where their ray enters it (FillGeometry, RefillGeometry). Defaults true
  // and 2 mm: past a reconstruction's edge the views see the skin at grazing angles, and the hull's entry lies
  // within 2 mm of it for most placed pixels (docs/geometry.md).
  bool geometry_hull = true;
  double geometry_hull_depth_mm = 2;
  // Worker threads; 0: one per core. Results do not depend on it.
  int threads = 0;
  // InvalidArgument naming the field.
  absl::Status Validate() const;
};

// Flags, per pixel.
enum PhotometricFlag : uint8_t {
  kSaturated = 1,        // some pattern image clipped
  kLowSignal = 2,        // too dark to solve (below min_signal_dn or min_signal_sigma)
  kBadFit = 4,           // the patterns disagree with a Lambertian surface (mislabeled or blended patterns, occlusion)
  kShadowed = 8,         // the geometry hides more than half of the full-on light from the point
  kNoSpecular = 16,      // no lobe measured: too faint, or reflecting off the dome
  kSpecularBadFit = 32,  // the specular images disagree with a GGX lobe
  kImplausible = 64,     // the albedo solved to more than max_albedo: left out of the albedo map, confidence 0
};

struct PhotometricMaps {
  int width = 0, height = 0;
  Image diffuse_normal_world;    // 3 channels, unit vectors, stage frame; 0 where not solved
  Image diffuse_normal_camera;   // the same in the camera frame
  Image albedo;                  // 3 channels, linear RGB (the images' channel order)
  Image specular_normal_world;   // 3 channels: the regularized specular normal, stage frame; 0 where not solved
  Image specular_normal_camera;  // the same in the camera frame
  Image specular_normal_raw;     // 3 channels, stage frame: each pixel's own fit, before regularization
  Image specular;                // 1 channel: specular intensity (GGX rho_s)
  Image roughness;               // 1 channel: GGX alpha (regularized)
  Image specular_sigma;          // 1 channel: the specular fit's standard deviation of the normal, degrees
  Image confidence;              // 1 channel, 0..1
  Image fit_residual;            // 1 channel: the diffuse fit's reduced chi-square (about 1 for a good fit)
  std::vector<uint8_t> flags;    // PhotometricFlag bits
  // The solvers' working memory (per pixel: the specular fit's noise, and the regularization's inputs), kept so that
  // the next solve of the same size reuses it.
  std::vector<float> work;
};

// Pixels of `g` the mesh misses, within options.geometry_fill_px of ones it covers and lit in the full-on image
// (`frames`, one per pattern, as SolvePhotometric takes them), placed at their neighbours' distance along their own ray
// (one ring a pass, each the mean of its placed 8-neighbours), with their shadows traced in the mesh from there (from
// options.shadow_clearance_mm off). A reconstruction ends where the cameras see the skin at grazing angles (the sides
// of the head, the neck); a pixel without a point sees the units from the stage origin, 0.1 m off there, and its fit
// fails. With `hull` (the frame's visual hull; null: none; options.geometry_hull), each placed pixel's distance is
// kept within the first stretch of its ray inside the hull about it, at most options.geometry_hull_depth_mm past its
// entry (g->hull_in, hull_out): past the mesh's edge the neighbours' distance lands in the air or centimetres behind
// the skin, where the hull's entry lies within millimetres of it. Returns how many pixels were placed, and marks them
// in g->placed.
absl::StatusOr<int64_t> FillGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, const LightModel& light,
                                     const std::vector<Image>& frames, const PhotometricOptions& options,
                                     PixelGeometry* g, const VisualHull* hull = nullptr);

// The pixels FillGeometry placed (g->placed), placed again along the surface the solved normals describe
// (`normals`: SolvePhotometric's diffuse_normal_world, 0 where not solved): ring by ring outwards from the pixels the
// mesh covers, each where its ray meets its set neighbours' tangent planes (the mean over those facing the ray), and
// their shadows traced again. A surface that turns away from the camera (the side of the head past a reconstruction's
// edge) is followed, where the neighbours' distance stays flat and lands millimetres off. Each distance is kept within
// the pixel's stretch of the visual hull, where FillGeometry found one. Returns the pixels placed.
absl::StatusOr<int64_t> RefillGeometry(const MeshBvh& mesh, const PhotometricCamera& camera, const LightModel& light,
                                       const Image& normals, const PhotometricOptions& options, PixelGeometry* g);

// `frames`: the cycle's images in pattern order (light.patterns), demosaiced RGB, DN above black. InvalidArgument
// names a missing pattern or a size mismatch. `geometry` (optional) must have the images' size.
absl::StatusOr<PhotometricMaps> SolvePhotometric(const LightModel& light, const std::vector<Image>& frames,
                                                 const PhotometricCamera& camera,
                                                 const PhotometricOptions& options = {},
                                                 const PixelGeometry* geometry = nullptr);

// SolvePhotometric in steps, for solving an image again where its geometry changed (RefillGeometry moves only the
// pixels FillGeometry placed): a pixel's fit reads only its own images and geometry, so SolveAgain keeps the fits of
// the pixels it is not asked to redo and runs only the passes over neighbourhoods (the albedo's demosaicing, the
// specular lobe's regularization) over the whole image again. Its maps equal SolvePhotometric's with the new geometry
// where the geometry changed nowhere else. `light`, `frames` and `camera` must outlive the solver, unchanged.
class PhotometricSolver {
 public:
  // InvalidArgument as SolvePhotometric's.
  static absl::StatusOr<std::unique_ptr<PhotometricSolver>> Create(const LightModel& light,
                                                                   const std::vector<Image>& frames,
                                                                   const PhotometricCamera& camera,
                                                                   const PhotometricOptions& options);
  ~PhotometricSolver();
  // Every pixel, with `geometry` (optional; the images' size) as SolvePhotometric. `again`: SolveAgain may follow (the
  // per-pixel fits are kept, memory of the maps' size); without it the fits become the maps, uncopied.
  absl::StatusOr<PhotometricMaps> Solve(const PixelGeometry* geometry, bool again = true);
  // After Solve(..., again): the pixels `redo` marks (non-zero; one per pixel) fitted again at `geometry`, the others'
  // fits kept.
  absl::StatusOr<PhotometricMaps> SolveAgain(const PixelGeometry& geometry, const std::vector<uint8_t>& redo);

 private:
  class Pixels;
  explicit PhotometricSolver(std::unique_ptr<Pixels> pixels);
  absl::Status CheckGeometry(const PixelGeometry* geometry) const;
  void SolvePixels(const PixelGeometry* geometry, const std::vector<uint8_t>* only);
  // The maps from per-pixel fits (fits_, a copy or moved): the passes over neighbourhoods run on them.
  PhotometricMaps Finish(PhotometricMaps m) const;

  std::unique_ptr<Pixels> pixels_;
  PhotometricMaps fits_;  // each pixel's own fit, before the passes over neighbourhoods
  bool solved_ = false;
};

// Angle between two unit vectors, degrees.
double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b);

}  // namespace stage::processing
