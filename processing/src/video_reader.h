// A video file's frames (or an image sequence's, as OpenCV's videoio names them), read by OpenCV's videoio in a module
// of its own, libstage_video_reader.so (stage/common/module.h): videoio brings FFmpeg, GStreamer and 95 more libraries
// into a process's start, and only `asset infer --video` reads a video.
#pragma once

#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/status.h"

namespace stage::processing::internal {

// Calls `fn` with each frame of the video at `path`, in order from 0, as width x height grey floats (the frames'
// values, 0..255 for 8-bit video; colour frames made grey), row-major and contiguous. NotFound when the file cannot
// be opened as a video; `fn`'s first error ends the reading and is returned.
using FrameFn = std::function<absl::Status(int64_t index, int width, int height, const float* grey)>;
using ReadVideoFn = absl::Status (*)(const std::string& path, const FrameFn& fn);
inline constexpr const char* kVideoReaderTarget = "stage_video_reader";
inline constexpr const char* kVideoReaderEntry = "StageReadVideo";

}  // namespace stage::processing::internal
