// A cycle of a camera's take as photometric stereo takes it in: the frames of one virtual frame (38 slots) read from
// the camera's HDF5 frame file (docs/storage.md), matched to the light model's patterns by name, demosaiced to linear
// RGB with the black level removed.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/processing/light_model.h"
#include "stage/processing/photometric.h"

namespace stage::processing {

struct CycleFrames {
  std::vector<Image> images;   // in the light model's pattern order
  std::vector<int64_t> slots;  // the slot each came from
  std::string camera_id;
  std::string pixel_format;
  int bits = 8;  // of the data (8, 12 or 16)
};

// Frame `frame` (slots [frame * cycle, (frame + 1) * cycle) of the take) of `path`. Errors name the file and what is
// wrong: a pattern of the cycle without a frame (lost, or not recorded), a pattern whose name in the file is not the
// light model's, a pixel format this does not read.
absl::StatusOr<CycleFrames> LoadCycle(const std::string& path, int64_t frame, const LightModel& light,
                                      double black_level_dn = 0);

}  // namespace stage::processing
