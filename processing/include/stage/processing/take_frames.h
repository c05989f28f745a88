// A cycle of a camera's take as photometric stereo takes it in: the frames of one virtual frame (38 slots) read from
// the camera's HDF5 frame file (docs/storage.md), matched to the light model's patterns by name, corrected (black
// level, flat field) and demosaiced to linear RGB.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/camera_model.h"
#include "stage/common/rig.h"
#include "stage/processing/light_model.h"
#include "stage/processing/photometric.h"

namespace stage::processing {

// One cycle of a camera, as recorded: a raw frame per pattern.
struct CycleFrames {
  int width = 0, height = 0;
  int bits = 8;  // of the data (8, 12 or 16)
  Mosaic mosaic;
  std::vector<std::vector<uint16_t>> raw;  // in the light model's pattern order, width x height each
  std::vector<int64_t> slots;              // the slot each came from
  std::string camera_id;
  std::string pixel_format;
};

// What is done to every raw frame before demosaicing.
struct RawCorrection {
  double black_level_dn = 0;
  // Each pixel's response relative to the mean (1 channel, the frames' size); null: uniform. Frames are divided by it.
  const Image* flat_field = nullptr;
};

// Frame `frame` (slots [frame * cycle, (frame + 1) * cycle) of the take) of `path`. Errors name the file and what is
// wrong: a pattern of the cycle without a frame (lost, or not recorded), a pattern whose name in the file is not the
// light model's, a pixel format this does not read.
absl::StatusOr<CycleFrames> LoadCycle(const std::string& path, int64_t frame, const LightModel& light);

// The cycle corrected (black level, flat field) and demosaiced to linear RGB (DemosaicBilinear), one image per
// pattern. InvalidArgument: a flat field of another size.
absl::StatusOr<std::vector<Image>> DemosaicCycle(const CycleFrames& cycle, const RawCorrection& correction = {});

// The frame file's size, data bits and camera, without reading frames.
struct FrameFileShape {
  int width = 0, height = 0, bits = 8;
  std::string camera_id, pixel_format;
  int64_t last_slot = -1;  // the highest slot stored
};
absl::StatusOr<FrameFileShape> ReadFrameFileShape(const std::string& path);

// A camera of a take as the stages read it: its frame file, its black level and its model at the recorded size.
struct TakeCamera {
  std::string id, path;
  CameraModel model;
  double black_level_dn = 0;
  int64_t last_slot = -1;  // the highest slot its file stores
};
// Cameras `ids` of the take in `take_dir` (recorded with `rig`), placed by `calibration` (null: the rig's nominal
// models). Errors name the file: a camera without a frame file, frames of a size the rig does not give.
absl::StatusOr<std::vector<TakeCamera>> OpenTakeCameras(const std::string& take_dir, const LoadedRig& rig,
                                                        const std::vector<std::string>& ids,
                                                        const CameraCalibration* calibration);

// Every frame of [first, last) of a camera's frame file that recorded a full-on pattern (every unit at 1; the
// cross-polarized one preferred): black level removed, demosaiced and averaged to grey, handed to `visit` in frame
// order (frames without one are skipped). Stops at the first error, of the file or of `visit`.
absl::Status ForEachFullLitFrame(const std::string& path, int64_t first, int64_t last, const LightModel& light,
                                 double black_level_dn,
                                 const std::function<absl::Status(int64_t frame, const Image& grey)>& visit);

// Bilinear demosaicing of a float mosaic (width x height, row-major) into RGB: each pixel keeps its own colour and
// takes the others as the mean of its nearest neighbours of that colour (mirrored at the borders).
void DemosaicBilinear(const float* mosaic, int width, int height, const Mosaic& layout, Image* rgb);

}  // namespace stage::processing
