// One camera's frames of one take as an HDF5 file (docs/storage.md): `/frames` (N, H, W) of 8- or 16-bit pixels,
// chunked one frame per chunk, and per-frame `frame_id`, `device_timestamp_ns`, `controller_time_ns`, `slot`,
// `pattern` and `status`; attributes for the camera, take, pixel format, exposure, gain and calibration.
//
// The writer runs HDF5's single-writer/multiple-reader mode (SWMR) and flushes every frame it appends: a reader may
// open the file while it is written, and a writer that dies (crash, SIGKILL, power loss of the process) leaves every
// frame appended before readable. Readers open such a file with FrameFileReader (or h5py's swmr=True; h5dump after
// `h5clear -s`).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/types/span.h"

namespace stage::storage {

// Per-frame status codes, as stored in `/status` (the ledger's words for them).
enum class FrameStatus : int32_t {
  kOk = 1,
  // Recorded, but some of its data never arrived (packet loss): the pixels are what arrived.
  kIncomplete = 2,
};

struct FrameRecord {
  uint64_t frame_id = 0;            // the camera's own frame counter
  int64_t device_timestamp_ns = 0;  // exposure start on the camera's clock
  int64_t controller_time_ns = 0;   // the same instant in controller time, ns since T0
  int64_t slot = 0;
  int32_t pattern = 0;
  FrameStatus status = FrameStatus::kOk;
};

struct FrameFileInfo {
  std::string camera_id;
  std::string take_id;
  uint32_t width = 0;
  uint32_t height = 0;
  // 1 (8-bit pixels) or 2 (16-bit words, little-endian as the PFNC formats are packed).
  uint32_t bytes_per_pixel = 1;
  std::string pixel_format;  // PFNC name, e.g. "BayerRG8"
  double exposure_us = 0;
  double gain_db = 0;
  // The camera's calibration as JSON (intrinsics, distortion, pose), or empty.
  std::string calibration_json;
  // The pattern cycle as JSON, [{"index", "name", "polarization"}...]: what each frame's `pattern` index means.
  std::string patterns_json;
};

class FrameFileWriter {
 public:
  // Creates `path` (refuses to overwrite an existing file); errors name the path and HDF5's reason.
  static absl::StatusOr<std::unique_ptr<FrameFileWriter>> Create(const std::string& path, const FrameFileInfo& info);
  ~FrameFileWriter();  // closes (errors are logged; call Close() to see them)

  // Appends one frame (`pixels`: width x height x bytes_per_pixel bytes) and makes it durable for readers. Space for
  // it is reserved first: a full disk is RESOURCE_EXHAUSTED before anything is written. After any error nothing more
  // can be appended (FAILED_PRECONDITION); what was appended before stays readable.
  absl::Status Append(const FrameRecord& record, absl::Span<const uint8_t> pixels);
  // Frames appended so far.
  int64_t frames() const { return frames_; }
  // Closes the file and gives back the space reserved beyond its end (ReleaseReservedSpace).
  absl::Status Close();

 private:
  FrameFileWriter() = default;
  // Takes the space the next frame of `frame_bytes` needs from the file system (RESOURCE_EXHAUSTED when it has none).
  absl::Status Reserve(size_t frame_bytes);
  struct Handles;
  std::string path_;
  FrameFileInfo info_;
  std::unique_ptr<Handles> h_;
  int64_t frames_ = 0;
  bool failed_ = false;
  uint64_t reserved_end_ = 0;  // the file is reserved up to here
  bool reserve_unsupported_ = false;
};

// Gives the file system back the space reserved beyond the end of frame file `path` (the writer reserves ahead of the
// frames it appends, without changing the file's size): what the file holds on disk is then its size, as `du` and
// the catalog count it. For a file whose writer closed it, and for one left by a writer that died (the controller
// recovers it). Errors name the path.
absl::Status ReleaseReservedSpace(const std::string& path);

class FrameFileReader {
 public:
  // Opens a file written by FrameFileWriter, also one still being written or left by a writer that died.
  static absl::StatusOr<std::unique_ptr<FrameFileReader>> Open(const std::string& path);
  ~FrameFileReader();

  const FrameFileInfo& info() const { return info_; }
  int64_t frames() const { return frames_; }
  // Every frame's record, in file order.
  absl::StatusOr<std::vector<FrameRecord>> Records() const;
  // Frame `index`'s pixels.
  absl::StatusOr<std::vector<uint8_t>> Pixels(int64_t index) const;

 private:
  FrameFileReader() = default;
  struct Handles;
  std::string path_;
  FrameFileInfo info_;
  std::unique_ptr<Handles> h_;
  int64_t frames_ = 0;
};

}  // namespace stage::storage
