// The trained asset driven from images (docs/asset.md#inference): each image of one camera cropped as the asset's
// dataset crops that camera's frames, encoded by the expression VAE, its expression latent mapped to the geometry
// latent (through the fine-tuned driving path where there is one), and decoded to the frame's UV geometry map (the
// head's frame, mm) and the face template's mesh at it. The camera may be one the expression VAE never trained on (the
// paper's held-out view) but must be one the dataset cropped, since its crop box and white are what place the face in
// its images with no pose known.
//
// Per frame, into the output directory's frame-NNNNNN/:
//   crop.png          the crop the nets saw (8-bit grey)
//   geometry_map.exr  the decoded map at the geometry VAE's resolution (stage/processing/uv_geometry.h's format)
//   mesh.obj          the face template with its vertices where the map puts them (its UVs kept)
// every `gltf_segment_frames` frames animation-<first frame>.glb, those frames' meshes as one glTF binary (the
// template with a morph target per frame and their animation: stage/processing/mesh_sequence.h), and frames.json
// (the camera, the source, the frames, the glTF files) once all are written.
// and, where the asset has a texture mapping (asset_train.h's TrainTextureMapping: the geometry latent to the texture
// latent), the frame's textures: albedo.exr (linear RGB), specular.exr and normal_tangent.exr (unit, +y along +v),
// float32 OpenEXR in the template's layout; where the dataset keeps the neutral frame's textures at full resolution
// (DatasetOptions::neutral_texture_size), at theirs: the decoded wrinkle maps (the decoded textures less the neutral
// frame's at the net's size) upsampled and added to them; else the decoded textures at the texture VAE's size.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace stage::processing {

struct AssetInferOptions {
  // The asset's dataset: its crop of `camera`, and the trained runs beside it.
  std::string dataset;
  // The runs (default: those the fine-tuning's run, else the mapping's, was trained from where they are still there,
  // else the dataset's directory/geometry, /expression, /mapping).
  std::string geometry_run, expression_run, mapping_run;
  // The fine-tuned driving path (asset_train.h's FineTuneDrivingAsset) the images drive through: its run; empty:
  // the dataset's directory/finetune where it holds a finished run, else the mapping; "none": the mapping.
  std::string finetune_run;
  // The texture mapping the textures are driven through (its run); empty: the dataset's directory/texture_mapping
  // where it holds a finished run, else no textures; "none": no textures. The texture VAE's run: `texture_run`
  // (default: the one the texture mapping was trained from where it is still there, else the dataset's
  // directory/texture).
  std::string texture_mapping_run, texture_run;
  // The camera the images are of (one the dataset cropped).
  std::string camera;
  // The images, from one of: a take's full-lit frames of the camera, frames [first_frame, last_frame) (last < 0: to
  // the end); or a video file (or an image sequence, "dir/frame-%04d.png") of the camera's view that OpenCV reads:
  // display-referred 8-bit frames at the camera's resolution, numbered from 0.
  std::string take_dir;
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  std::string video;
  // Default: TAKE/derived/asset/infer/<camera>, or beside the video: <its name without extension>-asset.
  std::string output_dir;
  bool meshes = true;  // false: no mesh.obj
  // Frames per glTF file (0: none). A file holds a morph target per frame: 240 frames of the template's 9,492
  // vertices are 27 MB, and Blender imports them as 240 shape keys.
  int gltf_segment_frames = 240;
  double gltf_frames_per_second = 24;  // the glTF animation's (the stage records 24 frames a second)
  int threads = 0;                     // torch's (0: the cores this process may use)
  // After each frame (frames done); asked before each: true stops (Cancelled; the frames written are kept, the
  // frames.json and the glTF file under way are not).
  std::function<void(int64_t)> progress;
  std::function<bool()> cancelled;
  absl::Status Validate() const;
};

struct AssetInferResult {
  std::string output_dir;
  std::vector<int64_t> frames;
  std::vector<std::string> gltf_files;  // in the output directory, in frame order
  bool textures = false;                // written per frame
  // Texels across them: the neutral frame's full-resolution textures' where the dataset keeps them (the wrinkle maps
  // upsampled and added to them), else the texture VAE's.
  int texture_size = 0;
};

// Errors name the file or the camera: no crop of the camera in the dataset, a run missing, a video that does not
// open or whose frames do not hold the camera's crop box.
absl::StatusOr<AssetInferResult> InferAsset(const AssetInferOptions& options);

}  // namespace stage::processing
