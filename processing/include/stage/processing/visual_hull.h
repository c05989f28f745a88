// The visual hull of a frame: the part of the stage inside every machine-vision view's silhouette (the subject's
// outline in its full-lit image). The subject lies inside it, so it bounds where a surface can be where no
// reconstruction reached: multi-view stereo writes each frame's silhouettes (derived/mvs/frame-N/silhouette/), and
// photometric stereo keeps the points it places beyond the mesh's edge inside the hull (docs/geometry.md).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/common/camera_model.h"

namespace stage::processing {

// One view's outline: the camera (at the mask's size, with its lens's distortion: the pixels as recorded) and, per
// pixel, 1 inside the subject's outline.
struct Silhouette {
  std::string id;
  CameraModel camera;
  std::vector<uint8_t> inside;  // camera.width() x camera.height(), row-major
};

// The silhouette of a linear grey image (`width` x `height`): the pixels at or above `min_signal`, with every hole
// closed (what the background does not reach from the image's border is inside: the nostrils, the mouth, the pupils),
// grown by `grow_px` pixels (a margin for the outline's own pixel). Empty when `grey` is not `width` x `height`.
std::vector<uint8_t> SilhouetteMask(const std::vector<float>& grey, int width, int height, float min_signal,
                                    int grow_px);

class VisualHull {
 public:
  VisualHull() = default;
  explicit VisualHull(std::vector<Silhouette> views) : views_(std::move(views)) {}

  // Writes `dir`/cameras.json (the views' cameras, a calibration file) and `dir`/ID.png per view (255 inside).
  static absl::Status Write(const std::string& dir, const std::vector<Silhouette>& views);
  // Reads what Write wrote. Errors name the file.
  static absl::StatusOr<VisualHull> Read(const std::string& dir);

  bool empty() const { return views_.empty(); }
  const std::vector<Silhouette>& views() const { return views_; }

  // Where stage point `p` (mm) lies: outside the outline of a view whose image it falls in, inside the outlines of
  // every such view, or in no view's image (a view that does not see p says nothing of it).
  enum class Seen { kOutside, kInside, kByNone };
  Seen Judge(const Eigen::Vector3d& p) const;

  // The first stretch of the ray origin + t * dir (dir unit) with t in [t0, t1] (finite) that no view puts outside
  // and some view sees inside, sampled every `step` mm and its ends found to step / 32: [*in, *out]. False when there
  // is none. A stretch no view sees (beyond their images) is no evidence of the subject and is passed over, unless it
  // runs into one some view sees inside, which it then widens. `entered` (optional): whether *in is where the ray
  // enters the hull from outside it, not where the search began nor where unseen air began.
  bool FirstSpan(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t0, double t1, double step,
                 double* in, double* out, bool* entered = nullptr) const;

 private:
  std::vector<Silhouette> views_;
};

}  // namespace stage::processing
