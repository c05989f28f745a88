// Camera calibration as a stage of the pipeline (docs/geometry.md): from a calibration take (the ChArUco board moved
// through the stage's volume), the board's corners found in every camera's full-lit frames, every camera and board
// pose started from the rig's nominal models, then one bundle adjustment over all cameras and board poses (Ceres,
// robust loss). Writes <take>/derived/calibration/cameras.json (a calibration file every later stage reads in place
// of the rig's models) and report.json. One code path for the library call, `stage-process calibrate` and the
// ProcessingWorker job (`stagectl calibrate`).
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/camera_calibration.h"
#include "stage/processing/photometric_stage.h"

namespace stage::processing {

struct CalibrationOptions {
  // Virtual frames [first_frame, last_frame) of the take; last_frame < 0: every whole cycle.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // Camera ids; empty: every camera of the take's rig.
  std::vector<std::string> cameras;
  // A view of the board counts with at least this many corners (>= 6: a pose from one view). Default 8.
  int min_corners = 8;
  // A camera needs the board in at least this many frames. Default 3.
  int min_frames = 3;
  // Huber loss scale of the bundle adjustment, pixels of the recorded images. Default 0.5.
  double loss_px = 0.5;
  // Fit the radial term k3 too. Default false (k3 kept at the rig's value).
  bool fit_k3 = false;
  // Every camera must be calibrated: false writes what could be calibrated and lists the rest in the report; true
  // (default) also fails the job, naming them.
  bool require_all = true;

  absl::Status Validate() const;
};

struct CalibrationJob {
  std::string take_dir;
  // Where cameras.json and report.json go; empty: <take_dir>/derived/calibration.
  std::string output_dir;
  CalibrationOptions options;
};

// A calibrated camera against the truth (the simulator's ground_truth/cameras.json), after the rigid motion that best
// fits all calibrated centres to the true ones (a calibration fixes the stage frame only up to such a motion).
struct CameraError {
  std::string id;
  double centre_mm = 0, rotation_deg = 0;
  double focal_percent = 0;  // (fx + fy) / 2 against the truth's, relative, %
  double principal_px = 0;   // sensor pixels
  double distortion_px = 0;  // RMS over the image of the lens terms' difference, sensor pixels
  // RMS distance between where the camera and its truth see the points of a 300 mm cube round the stage origin (the
  // head's volume), sensor pixels: what processing feels of the camera's error.
  double projection_px = 0;
};

struct TruthComparison {
  std::vector<CameraError> cameras;
  // The rigid motion from the calibration's frame to the truth's (a calibration fixes its frame only up to one): the
  // one under which the calibrated cameras see the head's volume most nearly as the true ones do, started from the best
  // fit of the centres. Its translation (mm) and angle (degrees).
  double frame_offset_mm = 0, frame_rotation_deg = 0;
  Eigen::Isometry3d to_truth = Eigen::Isometry3d::Identity();  // calibration's frame -> truth's
  // Worst over the cameras, and the root mean square.
  CameraError worst, rms;
};

struct CameraCalibrationReport {
  std::string id;
  int frames = 0, corners_used = 0, corners_dropped = 0;
  double rms_px = 0;         // reprojection RMS, pixels of the recorded images
  double rms_sensor_px = 0;  // the same in sensor pixels
  double coverage = 0;       // share of a 10 x 10 grid over the image with a corner in it
};

struct CalibrationReport {
  std::string take_dir, output_dir;
  double image_scale = 1;  // recorded pixels per sensor pixel
  int frames_read = 0, board_frames = 0, iterations = 0;
  double rms_px = 0;
  std::vector<CameraCalibrationReport> cameras;
  // Cameras left out, with why ("never saw the board in 72 frames").
  std::vector<std::pair<std::string, std::string>> missing;
  bool has_truth = false;
  TruthComparison truth;
  // The rig's nominal models against the truth: what calibration is to beat.
  TruthComparison nominal_truth;
  std::string solver;  // Ceres's brief report
};

// Runs the job: `progress` (may be empty) as frames are read and the fit runs; `cancelled` (may be empty) asked
// between cameras. Errors name the take, camera or file; with options.require_all, a camera that could not be
// calibrated fails the job by name after the others' calibration is written.
absl::StatusOr<CalibrationReport> RunCalibration(const CalibrationJob& job,
                                                 const std::function<void(const JobProgress&)>& progress = {},
                                                 const std::function<bool()>& cancelled = {});

// `calibrated` against `truth` (cameras in both; NotFound when none).
absl::StatusOr<TruthComparison> CompareCalibrations(const CameraCalibration& calibrated,
                                                    const CameraCalibration& truth);

// The take rig's nominal models as a calibration (whole sensors).
absl::StatusOr<CameraCalibration> NominalCalibration(const LoadedRig& rig);

// `stage-process evaluate calibration`: TAKE/derived/calibration/cameras.json (or `calibration`) against
// TAKE/ground_truth/cameras.json, beside the rig's nominal models against it.
struct CalibrationEvaluation {
  TruthComparison calibrated, nominal;
};
absl::StatusOr<CalibrationEvaluation> EvaluateCalibration(const std::string& take_dir,
                                                          const std::string& calibration = "");

std::string CalibrationReportJson(const CalibrationReport& report);
std::string FormatCalibrationReport(const CalibrationReport& report);
std::string TruthComparisonJson(const TruthComparison& comparison);
std::string FormatTruthComparison(const TruthComparison& comparison, const TruthComparison* nominal = nullptr);
std::string CalibrationEvaluationJson(const CalibrationEvaluation& evaluation);

}  // namespace stage::processing
