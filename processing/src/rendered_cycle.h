// One photometric cycle as a camera of the simulated stage records it, for tests against the ground truth: the 38
// patterns of virtual frame 0 rendered in process (12-bit Bayer RGGB), demosaiced as the pipeline does, the camera
// resolved as the pipeline resolves it (calibration.h, placed where it truly is), and per pixel the truth the renderer
// used (with sim.supersample, the mean over the pixel's rays, as the sensor integrates them).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "stage/processing/photometric.h"
#include "stage/sim/light_transport.h"
#include "stage/sim/scene.h"

namespace stage::processing {

struct RenderedCycle {
  LightModel light;
  std::vector<Image> frames;     // the demosaiced patterns, black level removed (DN)
  PhotometricCamera camera;      // as the pipeline resolves it
  int index = -1;                // the camera's in the scene
  std::vector<sim::Hit> hits;    // per pixel; not hit where the subject does not fill the pixel
  PixelGeometry truth_geometry;  // from the simulator's own subject: where each pixel lands, what it sees
  std::shared_ptr<const sim::SimScene> scene;
};

// Renders the cycle for camera `camera_id` of the built-in rig at render scale 1/8, the subject still, with
// `overrides` (rig overrides) after those. Fails the calling test on an error.
void RenderCycle(const std::string& camera_id, const std::vector<std::string>& overrides, RenderedCycle* out);

}  // namespace stage::processing
