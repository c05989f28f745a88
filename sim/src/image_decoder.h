// The head asset's image files decoded (PNG, JPEG, TIFF, OpenEXR), by OpenCV's image codecs in a module of their own,
// libstage_sim_images.so (stage/common/module.h): the codecs bring GDAL and 80 more libraries, 57 % of a camera node's
// symbol relocations at its start, and a node never decodes an asset itself (the first process that loads one writes
// the decoded maps to a cache file that every other maps: head.cc).
#pragma once

#include <string>
#include <vector>

#include "absl/status/status.h"

namespace stage::sim::internal {

struct DecodedImage {
  int width = 0, height = 0;
  // Integer images are mapped to [0, 1] (8 and 16 bit); float images (OpenEXR) are as they are.
  bool integer = true;
  std::vector<float> texels;  // row-major from the top, `channels` a texel, RGB order
};

// Decodes `path` into `channels` (1: grey, 3: RGB) floats. InvalidArgument without the file's name (the caller names
// it and its rig field): "cannot read it (...)" or "neither 8 nor 16-bit nor float".
using DecodeImageFn = absl::Status (*)(const std::string& path, int channels, DecodedImage* out);
inline constexpr const char* kSimImagesTarget = "stage_sim_images";
inline constexpr const char* kSimImagesEntry = "StageSimDecodeImage";

}  // namespace stage::sim::internal
