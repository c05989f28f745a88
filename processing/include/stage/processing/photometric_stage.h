// Photometric stereo as a stage of the pipeline (docs/processing.md): over a take's frames and cameras, each camera's
// cycle read from its frame file, solved (photometric.h) and written to <take>/derived/photometric/ as OpenEXR maps,
// PNG previews, a metrics JSON and a contact sheet. One code path for the three ways it runs: this library call, the
// batch command (`stage-process photometric`) and the ProcessingWorker service (`stagectl process`).
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/rig.h"
#include "stage/processing/photometric.h"

namespace stage::processing {

// Where photometric stereo's surface geometry comes from (v1::GeometrySource at the RPC edge).
enum class GeometrySource {
  kMvs,        // multi-view stereo's meshes, <take>/derived/mvs (mvs.h): the default
  kNone,       // none: every pixel sees the units from the stage origin (the table-driven solver can run)
  kDirectory,  // a directory of frame-NNNNNN/mesh.obj (the simulator's ground_truth/: the truth's)
};

struct GeometrySpec {
  GeometrySource source = GeometrySource::kMvs;
  // With kDirectory: the directory, relative to the take directory or absolute; empty otherwise.
  std::string dir;

  // "mvs", "none", or a directory (the command lines' --geometry).
  static GeometrySpec Parse(const std::string& flag);
  // The inverse of Parse, for run.json and logs.
  std::string ToString() const;
  // A directory with kDirectory, none otherwise.
  absl::Status Validate() const;
  // Where the meshes are, as given (relative to the take, or absolute; normalized): derived/mvs for kMvs, the
  // directory for kDirectory, empty for kNone. And that directory in the take `take_dir`.
  std::string RelativeDir() const;
  std::string Root(const std::string& take_dir) const;
  bool has_mesh() const { return source != GeometrySource::kNone; }
};

struct PhotometricJob {
  // The take directory (takes/<take-id>, with take.json and cameras/<camera>.h5).
  std::string take_dir;
  // Virtual frames [first_frame, last_frame); last_frame < 0: every whole cycle the take recorded.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // Camera ids; empty: every high-speed camera of the take's rig.
  std::vector<std::string> cameras;
  // Surface geometry: meshes (stage frame, mm) per frame of the take; by default multi-view stereo's, which must have
  // run first (a take without them is refused, naming the directory).
  GeometrySpec geometry;
  // Where the cameras are: a calibration file (camera_calibration.h), or a directory holding one as cameras.json
  // (`stage-process calibrate`'s output, or the simulator's ground_truth/), relative to the take directory or
  // absolute. Empty: the rig's nominal models (uncalibrated; said so in run.json).
  std::string calibration;
  // Where the results go; empty: <take_dir>/derived/photometric.
  std::string output_dir;
  // Without geometry the table-driven solver runs (fast_photometric.h); true: the per-pixel one (photometric.h)
  // regardless. With geometry the per-pixel one always runs.
  bool exact = false;
  PhotometricOptions options;
};

struct JobProgress {
  int64_t done = 0, total = 0;  // units: one camera's frame
  std::string message;
};

struct JobResult {
  std::string output_dir;
  int64_t units = 0;
};

// Runs the job; `progress` (may be empty) after each unit; `cancelled` (may be empty) is asked before each unit, and
// true ends the job with CANCELLED (the units done so far stay written). Errors name the take, frame, camera or file.
absl::StatusOr<JobResult> RunPhotometric(const PhotometricJob& job,
                                         const std::function<void(const JobProgress&)>& progress = {},
                                         const std::function<bool()>& cancelled = {});

// The rig a take was recorded with (its take.json), for reading the take.
absl::StatusOr<LoadedRig> LoadTakeRig(const std::string& take_dir);

// A path a job names in its take: `path` itself when absolute, else under `take_dir`; `fallback` (under `take_dir`)
// when `path` is empty, and empty when both are.
std::string PathInTake(const std::string& take_dir, const std::string& path, const std::string& fallback = "");

// The calibration `spec` names (PhotometricJob::calibration: a file, or a directory with cameras.json, relative to
// `take_dir` or absolute); nullopt for an empty spec. Errors name the path.
absl::StatusOr<std::optional<CameraCalibration>> LoadJobCalibration(const std::string& take_dir,
                                                                    const std::string& spec);

// The directory of frame `frame` under a stage's output root (frame-NNNNNN), and of its camera `camera` in it.
std::string FrameDir(const std::string& root, int64_t frame);
std::string UnitDir(const std::string& root, int64_t frame, const std::string& camera);
// The end of the run of frames from `first` under `root` that hold `file` (FrameDir(root, f)/file): the first frame
// at or after `first` without it.
int64_t EndOfFrames(const std::string& root, const std::string& file, int64_t first);

}  // namespace stage::processing
