// A take rendered straight from the simulator's scene, without bringing the stage up: what the stage would record
// of the chosen frames and patterns (each camera's raw frames, packed as its pixel format, in the take's own frame
// files), with the take file processing reads the rig from and the ground truth beside. Quick where a whole take is
// slow: a neural asset's long performance needs only each machine-vision camera's full-lit frame every few frames
// (docs/asset.md#a-performance-to-learn-from). The layout is a recorded take's (docs/storage.md):
//   DIR/take.json               format, take id, state "rendered", the rig (with defaults applied)
//   DIR/cameras/<camera>.h5     frame files; slot = frame x cycle + pattern, as the stage's schedule numbers them
//   DIR/ground_truth/           WriteGroundTruth's, for the same frames (without the per-camera maps and meshes
//                               unless asked)
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "stage/sim/scene.h"

namespace stage::sim {

struct RenderedTakeOptions {
  // Virtual frames [first_frame, last_frame), every frame_step-th.
  int64_t first_frame = 0;
  int64_t last_frame = 1;
  int64_t frame_step = 1;
  // Camera ids; empty: every machine-vision camera.
  std::vector<std::string> cameras;
  // Only the full-on patterns (every unit at 1; one a polarization state the schedule has), or every pattern.
  bool full_lit_only = true;
  // The ground truth's extras (ground_truth.h): per-camera maps, meshes, the UV position map's size.
  bool truth_camera_maps = false;
  bool truth_meshes = false;
  // The truth's skin textures in UV too (GroundTruthOptions::uv_textures).
  bool truth_textures = false;
  int uv_size = 512;
  // Renderer threads (0: one per core).
  int threads = 0;
  // Called after each camera of each frame: (done, total).
  std::function<void(int64_t, int64_t)> progress;
  absl::Status Validate() const;
};

// Writes the take into `dir` (which must not hold one). Errors name the camera, file or option.
absl::Status WriteRenderedTake(std::shared_ptr<const SimScene> scene, const std::string& dir,
                               const RenderedTakeOptions& options);

}  // namespace stage::sim
