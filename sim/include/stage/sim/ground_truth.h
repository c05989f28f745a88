// Ground truth of the simulated stage (docs/simulator.md): what processing results are judged against.
//   DIR/cameras.json                    every camera where it really is (a calibration file, camera_calibration.h)
//   DIR/frame-NNNNNN/pose.json          expression weights (head), rotation and translation, stage_from_head (the
//                                       head's frame to the stage's, row-major 4 x 4, mm), time, the performance's
//                                       sequence; for the calibration board its layout and ChArUco corners (stage
//                                       frame, mm)
//   DIR/frame-NNNNNN/mesh.obj           the posed subject mesh (stage frame, mm), with texture coordinates
//   DIR/frame-NNNNNN/uv_position.exr    stage-frame position (mm) per texel of the skin's UV map; alpha 1 where covered
//   DIR/frame-NNNNNN/uv_albedo.exr      with uv_textures: the skin's diffuse albedo (linear RGB) per texel of the same
//                                       map, as the expression has it (the open mouth's dark); alpha 1 where covered
//   DIR/frame-NNNNNN/uv_material.exr    specular intensity (R) and roughness (G, GGX alpha) per texel
//   DIR/frame-NNNNNN/uv_normal.exr      the shading normal with its pore and wrinkle detail per texel, in the head's
//                                       frame (the pose taken out: what the renderer shades with, turned back)
//   DIR/frame-NNNNNN/<camera>/depth.exr        distance along the camera's optical axis, mm (0: no subject)
//   DIR/frame-NNNNNN/<camera>/normal_world.exr shading normal (with pore and wrinkle detail), stage frame
//   DIR/frame-NNNNNN/<camera>/normal_camera.exr the same in the camera frame (x right, y down, z forward)
//   DIR/frame-NNNNNN/<camera>/albedo.exr       diffuse albedo, linear RGB
//   DIR/frame-NNNNNN/<camera>/specular.exr     specular intensity;   roughness.exr: GGX alpha
//   DIR/frame-NNNNNN/<camera>/mask.png         255 where the pixel sees the subject (with sim.supersample n > 1: all
//                                              of its n x n rays meet it; 128 where only some do, at its edge)
// Images are at the rig's render scale, float32 OpenEXR (channels in R, G, B order of the values above). A pixel of
// n x n rays has the mean of their materials and their mean normal, normalized: the area its value integrates.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "stage/sim/scene.h"

namespace stage::sim {

struct GroundTruthOptions {
  // Virtual frames [first, last).
  int64_t first_frame = 0;
  int64_t last_frame = 1;
  // Every frame_step-th frame of them, from first_frame (1 and up).
  int64_t frame_step = 1;
  // Camera ids; empty: every camera.
  std::vector<std::string> cameras;
  // Directories are numbered frame - name_offset (a take's frames from 0: its first world frame).
  int64_t name_offset = 0;
  // Texels across the UV position map (16..16384).
  int uv_size = 256;
  // Every camera's per-pixel maps (depth, normals, materials: two thirds of the time); false: the true cameras and
  // each frame's subject only (`cameras` is then unused).
  bool camera_maps = true;
  // The posed mesh as mesh.obj (4 MB a frame at the head's default resolution); false: uv_position.exr only holds
  // the surface (a long performance for a neural asset's dataset).
  bool meshes = true;
  // The skin's textures in the same UV layout (uv_albedo, uv_material, uv_normal): what a neural asset's texture
  // branch learns (docs/asset.md).
  bool uv_textures = false;
  // Called after each camera of each frame: (done, total).
  std::function<void(int, int)> progress;
  // Frames not empty, a step of 1 or more, the map's size in range (the cameras are checked against the scene's rig).
  absl::Status Validate() const;
};

absl::Status WriteGroundTruth(const SimScene& scene, const std::string& dir, const GroundTruthOptions& options);

// The skin's material and detailed shading normal per texel of its UV layout (part 0 of `model`) under `pose`'s
// expression, size x size, RGBA each (alpha 1 where covered, row 0 at v = 1): albedo (linear RGB), specular intensity
// and roughness (R, G), and the shading normal in the head's frame (unit; bump or normal-mapped detail on the posed
// mesh's smooth normal, as the renderer shades).
struct UvMaterialMaps {
  std::vector<float> albedo, material, normal;
};
UvMaterialMaps UvMaterials(const RiggedModel& model, const HeadPose& pose, int size);

// Stage-frame position per texel of the skin (part 0) of `mesh`, size x size, RGBA (alpha 1 where covered); row 0 at
// v = 1 (stage/common/uv_raster.h).
std::vector<float> UvPositionMap(const TriangleMesh& mesh, int size);

}  // namespace stage::sim
