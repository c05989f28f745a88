// Previews: a frame shrunk to a few hundred pixels and PNG-encoded, for the console during a take (no full frame
// crosses the controller). OpenCV (the shrinking) and libpng stay inside preview.cc.
#pragma once

#include <cstdint>

#include "absl/status/statusor.h"
#include "stage/camera/camera_device.h"
#include "stage/v1/camera_node.pb.h"

namespace stage::camera {

// The frame (8- or 16-bit, one channel; 16-bit scaled by its own peak) with its longest side at most `max_size`,
// as an 8-bit PNG; metadata left for the caller. InvalidArgument for an empty or malformed frame.
absl::StatusOr<v1::Preview> MakePreview(const Frame& frame, uint32_t max_size);

}  // namespace stage::camera
