// UV texture fusion (docs/assets.md#texture-fusion): the photometric maps of several cameras (the three high-speed
// views) resampled into the fitted template's UV layout and blended, each view weighted by how squarely it sees the
// point, the photometric solve's confidence there, and how far the point lies from the edge of what that view sees
// (an occluding contour, the end of its maps), so seams between views fade rather than step. Normals are fused in the
// head's frame (object space) and also given in tangent space. The texel convention is stage/common/uv_raster.h's.
//
// Tangent space: per vertex, the tangent is the direction of increasing u over the surface (accumulated over the
// vertex's triangles, weighted by their UV-to-surface Jacobians as Lengyel's method does) made orthogonal to the
// vertex normal; the bitangent is normal x tangent, signed to point towards increasing v (OpenGL's "Y+" convention,
// which Blender's normal map node reads). Per texel the three are interpolated and made orthonormal again. This is
// not MikkTSpace (Debian has none), which differs in how it weights a vertex's triangles; on a smooth template the
// two agree to a fraction of a degree.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/common/camera_model.h"
#include "stage/common/mesh.h"
#include "stage/processing/photometric.h"
#include "stage/processing/photometric_stage.h"
#include "stage/processing/uv_geometry.h"

namespace stage::processing {

struct FusionOptions {
  // Texels across the square textures (16..16384).
  int size = 4096;
  // The mesh's part fused (0: skin; -1 every part).
  int part = 0;
  // Views seeing the surface more obliquely than this (degrees from its normal) weigh nothing (1..89).
  double max_view_angle_deg = 75;
  // A view's specular lobe (its specular normal, intensity and roughness; of every view, with specular normals or
  // without) is fused only where the view sees the surface within this many degrees of its normal, its weight fading
  // to nothing over the last 5 degrees (1..89; the diffuse maps go to max_view_angle_deg): the solve's specular normal
  // tilts towards the camera the more obliquely it sees the skin (1-1.5 deg at 30-45 deg, 2-5 at 45-60, 5-13
  // beyond; docs/assets.md#fusing-the-photometric-solves), a bias that averaging views does not remove.
  double max_lobe_view_angle_deg = 50;
  // A pixel of a view whose photometric confidence is below this is not used (0..1).
  double min_confidence = 0.05;
  // A view's weight rises from 0 at the edge of what it sees (an occluding contour, the end of its maps) to full at
  // this many of its pixels from it (0: no feathering; ..256).
  double feather_px = 8;
  // A point more than this behind the first surface its camera sees along the ray is hidden from it, mm (> 0).
  double occlusion_mm = 1.0;
  // Neighbouring pixels whose depths differ by more than this meet at an occluding contour, mm (> 0).
  double contour_mm = 4.0;
  // Rings of texels grown past the covered ones (seams and the layout's edges; 0..64).
  int dilation_px = 8;

  absl::Status Validate() const;
};

// One camera's photometric maps (PhotometricMaps' images: width x height of the camera's model) and where the camera
// is. Optional maps are empty images (width 0).
struct FusionView {
  std::string camera_id;
  CameraModel camera;     // at the maps' size
  Image albedo;           // 3 channels, linear RGB
  Image diffuse_normal;   // 3 channels, unit, stage frame; 0 where not solved
  Image specular;         // 1 channel (optional)
  Image roughness;        // 1 channel (optional)
  Image specular_normal;  // 3 channels, stage frame (optional)
  Image confidence;       // 1 channel, 0..1 (optional: 1 wherever the normal is solved)
};

struct FusedTextures {
  int size = 0;
  Image albedo;                  // 3 channels
  Image specular;                // 1 channel (0 where no view has one)
  Image roughness;               // 1 channel
  Image normal_object;           // 3 channels: the diffuse normal in the head's frame, unit; 0 where empty
  Image normal_tangent;          // 3 channels: the same in tangent space, unit; 0 where empty
  Image specular_normal_object;  // 3 channels (0 where no view has one)
  Image specular_normal_tangent;
  Image weight;  // 1 channel: the views' summed weight (0: from the dilation, or nothing)
  // 1 channel: the weight of the views that measured a specular lobe there (their specular normal solved). Where it
  // is 0 on a covered texel the specular maps are filled: the specular normal is the diffuse one, the intensity and
  // roughness the neighbourhood's typical values (medians of 16 x 16-texel cells, smoothed over a few cells). A
  // measured lobe more than 4 times off those (the solve's isolated bad fits) is filled the same way.
  Image specular_weight;
  int64_t lobes_rejected = 0;            // texels whose measured lobe was such an outlier
  std::vector<TexelState> state;         // covered: some view saw it; dilated: grown from neighbours; empty
  std::vector<uint8_t> views;            // per texel, how many views saw it
  std::vector<int64_t> texels_per_view;  // texels each view contributed to (views' order)
};

// Fuses `views` into the UV layout of `mesh` (the fitted template: stage frame, mm, a uv per vertex). Normals are
// taken to the head's frame by `head_from_stage`. Errors: options out of range, a mesh without texture coordinates,
// a view whose maps' sizes differ from its camera's or lack the albedo or diffuse normal (named by camera id).
absl::StatusOr<FusedTextures> FuseTextures(const TriangleMesh& mesh, const Eigen::Isometry3f& head_from_stage,
                                           const std::vector<FusionView>& views, const FusionOptions& options);

// Fused textures against a reference of the same layout and size (the truth's maps fused with the same views'
// weights), on the texels both cover: the albedo's relative error (per texel the mean over its channels of
// |fused / truth - 1|), the normals' angles in the head's frame; where both measured a specular lobe
// (specular_weight > 0) the specular normals' angles, the intensity's relative error (median: a lobe's intensity is
// the noisiest of the maps) and the roughness's absolute error.
struct TextureErrors {
  int64_t texels = 0;
  double albedo_mean = 0, albedo_median = 0;
  double normal_mean_deg = 0, normal_median_deg = 0, normal_p90_deg = 0;
  int64_t specular_texels = 0;
  double specular_normal_mean_deg = 0, specular_normal_median_deg = 0;
  double specular_median = 0, roughness_mean = 0;
};
// Errors: sizes that differ. `mask` (optional, size x size): only texels where it is true count.
absl::StatusOr<TextureErrors> CompareTextures(const FusedTextures& fused, const FusedTextures& truth,
                                              const std::vector<bool>* mask = nullptr);

// The stage (docs/assets.md#texture-fusion-as-a-stage): per frame, the fitted template (TAKE/derived/fit) and the
// views' photometric maps (TAKE/derived/photometric/frame-NNNNNN/<camera>/) fused into
// TAKE/derived/textures/frame-NNNNNN/: OpenEXR textures, PNG previews, a contact sheet and metrics.json.
struct TexturesJob {
  std::string take_dir;
  // Frames [first_frame, last_frame); last_frame < 0: up to the last the fit holds without a gap.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // The views; empty: every camera with photometric maps in the first frame.
  std::vector<std::string> cameras;
  // Where the cameras are: a calibration file or a directory with cameras.json, relative to the take or absolute;
  // empty: the rig's nominal models.
  std::string calibration;
  // Where the inputs are and the results go, relative to the take or absolute; empty: derived/fit,
  // derived/photometric and derived/textures.
  std::string fit_dir, photometric_dir, output_dir;
  FusionOptions options;

  // The take named, a frame range that can hold frames, camera ids not empty, and the options.
  absl::Status Validate() const;
};

// A frame's textures as the stage writes them (`dir`: the EXR textures, PNG previews, a contact sheet titled `title`,
// `metrics_json`), and read back (the texel states from the weights: covered where a view saw it, dilated where only
// the dilation put a normal; the view counts are not written). Errors name the file.
absl::Status WriteFusedTextures(const std::string& dir, const FusedTextures& textures, const std::string& metrics_json,
                                const std::string& title);
absl::StatusOr<FusedTextures> ReadFusedTextures(const std::string& dir);

// One view's photometric maps as the stage reads them (PhotometricMaps' files in `dir`: albedo, diffuse and specular
// normals, specular, roughness, confidence), its camera placed by `calibration` (nullptr: the rig's nominal model) at
// their size. Errors name the file.
absl::StatusOr<FusionView> LoadFusionView(const LoadedRig& rig, const CameraCalibration* calibration,
                                          const std::string& dir, const std::string& id);
// A frame's pose (a pose.json with stage_from_head: the fit's, or the simulator's truth) as head_from_stage. Errors
// name the file.
absl::StatusOr<Eigen::Isometry3f> HeadFromStage(const std::string& pose_file);

absl::StatusOr<JobResult> RunTextures(const TexturesJob& job,
                                      const std::function<void(const JobProgress&)>& progress = {},
                                      const std::function<bool()>& cancelled = {});

// Per vertex of `mesh`, the unit tangent (towards increasing u, orthogonal to the vertex normal) and in w the
// bitangent's sign: +1 where normal x tangent points towards increasing v. Needs a uv per vertex.
std::vector<Eigen::Vector4f> VertexTangents(const TriangleMesh& mesh, const std::vector<Eigen::Vector3f>& normals);

// The depth (along the camera's optical axis, mm) of the first surface of `mesh` each pixel of `camera` sees,
// +infinity where none: a z-buffer of the mesh's triangles projected through the camera's lens.
std::vector<float> DepthBuffer(const TriangleMesh& mesh, const CameraModel& camera);

}  // namespace stage::processing
