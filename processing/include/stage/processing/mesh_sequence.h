// A mesh of one topology moving over frames (the face template driven by the neural asset, docs/asset.md#export)
// written as one glTF 2.0 binary file (.glb) that Blender, three.js and the like import as an animation.
//
// The layout: one mesh (the rest positions, its smooth vertex normals, the triangles, the texture coordinates) with
// one morph target per frame (its positions less the rest's), and one animation of the morph weights: at frame k's
// time (k / frames per second) target k weighs 1 and every other 0, linear between keys, so the mesh passes through
// every frame's positions.
// Blender imports the targets as shape keys named `frame-NNNNNN` (the mesh's extras.targetNames).
//
// Units and axes: glTF's are metres, +y up, +z the front of the asset, +x its left: the head frame's axes (+y up,
// +z the way the face looks, +x the performer's left), so positions in mm are only scaled by 1/1000. Texture
// coordinates are flipped to glTF's top-left origin (v' = 1 - v). With textures (MeshSequenceOptions), one material
// (metallic 0, roughness 0.5) holds them.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "stage/common/mesh.h"

namespace stage::processing {

struct MeshSequenceOptions {
  double frames_per_second = 24;  // the animation's keys' spacing; > 0
  std::string generator;          // the file's asset.generator (default: "FaStage")
  // The mesh's material, its textures in the mesh's UV layout as PNG files' bytes, embedded in the file: the base
  // colour (sRGB) and the normal map (tangent space, +y along +v: glTF's convention), rows from v = 1 down (as the
  // project's textures are stored; glTF's top-left origin). Empty: no material (the normal map only with a colour).
  std::string base_color_png, normal_png;
  absl::Status Validate() const;
};

// One frame of the sequence: its number (the target's name) and the positions of the rest mesh's vertices (mm).
struct MeshSequenceFrame {
  int64_t frame = 0;
  std::vector<Eigen::Vector3f> positions;
};

// Writes `frames` over `rest` (its positions in mm, triangles, per-vertex uvs when it has them) to `path`,
// atomically. Errors name the path, or the frame whose vertex count is not the rest mesh's.
absl::Status WriteMeshSequenceGlb(const std::string& path, const TriangleMesh& rest,
                                  const std::vector<MeshSequenceFrame>& frames,
                                  const MeshSequenceOptions& options = {});

}  // namespace stage::processing
