// The face template fitted to a frame's surface (docs/assets.md#the-fit): a rigid alignment (point-to-plane ICP)
// from the previous frame's pose; with the template's shape and expression model, a fit of its coefficients and the
// pose together; then non-rigid ICP: every vertex drawn to the nearest point of the surface (along the rest shape's
// normal once the model has placed the skin), held to the rest shape by a membrane whose stiffness falls stage by
// stage (Eigen's sparse Cholesky). The eyes' and the mouth's openings follow their neighbours (no data term there).
// Evaluation against the simulator's truth maps every template vertex to the true surface through the head's UV
// layout, so sliding along the surface is measured apart from distance to it.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/common/mesh.h"
#include "stage/processing/face_template.h"
#include "stage/processing/photometric_stage.h"
#include "stage/processing/uv_geometry.h"

namespace stage::processing {

// How the non-rigid stages may move a vertex from the rest shape.
enum class NonRigidMotion : uint8_t {
  kAuto = 0,         // along the normal when the template has a model and it is fitted, freely otherwise
  kFree = 1,         // anywhere: the membrane and the nearest points alone decide where along the surface it goes
  kAlongNormal = 2,  // along the rest shape's normal only: the model places the skin, the membrane adds detail
};
const char* NonRigidMotionName(NonRigidMotion m);  // "auto", "free", "along_normal"
// The motion named by NonRigidMotionName, or an error naming the word.
absl::StatusOr<NonRigidMotion> ParseNonRigidMotion(const std::string& name);

struct TemplateFitOptions {
  // Placement ICP iterations (point-to-plane, Gauss-Newton over rotation, translation, the jaw's turn unless the
  // template's expression blendshapes are fitted, and with fit_scale a uniform scale about the head's origin).
  int rigid_iterations = 30;
  // Fit a uniform scale; not used when the template's identity model is fitted (its components carry the head's
  // size, and a free scale would trade with them from frame to frame).
  bool fit_scale = true;
  // Membrane stiffness of the non-rigid stages, from the first (stiff: the template's shape, placed) to the last
  // (supple: the surface's detail); each is a weight against the data term's 1 per vertex.
  std::vector<double> stiffness = {50, 15, 5, 1.5, 0.5};
  // Correspondence updates per non-rigid stage.
  int iterations_per_stage = 3;
  // Correspondences further than this from the surface are left out, mm (the surface's holes and edges).
  double max_distance_mm = 8;
  // Correspondences whose surface normal turns further than this from the template's are left out, degrees.
  double max_normal_angle_deg = 60;
  // Leave out correspondences on the surface's border (triangles touching an edge of one triangle: a hole's rim or
  // the mesh's edge), which would draw the vertices over a hole to its rim.
  bool skip_border = true;
  // How the non-rigid stages may move a vertex from the rest shape.
  NonRigidMotion nonrigid = NonRigidMotion::kAuto;
  // The model's fit, between placement and non-rigid ICP, when the template has a model (docs/assets.md#the-model):
  // Gauss-Newton iterations over the pose and the identity and expression coefficients together (and the jaw's turn
  // when there are no blendshapes), the correspondences updated each time; 0: no model fit (the template's own
  // shape, scaled and jawed by the placement, is the rest shape).
  int model_iterations = 20;
  // The coefficients' priors (ridge weights toward 0, the template's neutral face), in vertices: a coefficient of one
  // standard deviation (identity) or a whole blendshape (expression) costs as much as this many vertices off their
  // planes by the fit's typical residual (the median's, each step). On a surface the model meets exactly the priors
  // fade; on a noisy one (multi-view stereo's) they hold the coefficients from fitting its noise.
  double identity_prior = 100, expression_prior = 1;
  // The identity's coefficients are kept within this many standard deviations; the expression's within [0, 1] (a
  // blendshape's weight, none to full).
  double identity_reach = 3;

  absl::Status Validate() const;
};

struct TemplateFit {
  // The template's vertices on the surface, stage frame, mm (the template's topology).
  std::vector<Eigen::Vector3f> positions;
  // The rigid part: the head frame to the stage's; and the template's scale about the head's origin (the performer's
  // head against the template's).
  Eigen::Isometry3f stage_from_head = Eigen::Isometry3f::Identity();
  float scale = 1;
  // How far the jaw is turned about its hinge from the template's (radians; the template's jaw weights).
  float jaw_rad = 0;
  // The model's coefficients (empty: no model fitted): identity in standard deviations (the drawn faces' RMS about
  // the template), expression in blendshape weights.
  std::vector<float> identity, expression;
  // Over the vertices with a correspondence at the end: their distance to the surface, RMS, mm; and their count.
  double rms_mm = 0;
  int64_t matched = 0;
};

// Fits `face` to `surface` (stage frame, mm), starting at `start` (the previous frame's fit; or the template at a
// guessed pose: `StartAt`). Errors: options out of range, an empty surface, no vertex near the surface.
absl::StatusOr<TemplateFit> FitTemplate(const FaceTemplate& face, const TriangleMesh& surface, const TemplateFit& start,
                                        const TemplateFitOptions& options = {});

// The template's neutral shape placed by `stage_from_head`: a first frame's start.
TemplateFit StartAt(const FaceTemplate& face, const Eigen::Isometry3f& stage_from_head);

// A fit against the simulator's truth: `truth` is the performer's posed mesh (stage frame) with the head's skin layout,
// so template vertex i belongs at the truth's point at face.HeadLayoutUv(uv_i).
struct FitError {
  int64_t vertices = 0;
  double rmse_mm = 0, p99_mm = 0;                  // distance to where the vertex belongs
  double surface_rmse_mm = 0;                      // its part along the true surface's normal
  double sliding_rmse_mm = 0, sliding_p99_mm = 0;  // its part along the surface
};
struct FitEvaluation {
  FitError skin, eyes, mouth;
};
absl::StatusOr<FitEvaluation> EvaluateFit(const FaceTemplate& face, const TemplateFit& fit, const TriangleMesh& truth);

// The template placed exactly on the truth (the perfect fit, for checking what comes after the fit): every vertex
// at the truth's point at face.HeadLayoutUv(uv). Errors: a vertex whose point the truth's layout does not cover.
absl::StatusOr<TriangleMesh> TemplateOnTruth(const FaceTemplate& face, const TriangleMesh& truth);

// The fit as a stage of the pipeline: over a take's frames, the template tracked through the surfaces (each frame's
// fit starting from the one before; the first from the head at the stage's origin, facing +z), written to
// <take>/derived/fit/frame-NNNNNN/: mesh.obj (the template's topology and UVs, stage frame, mm), geometry_map.exr
// (uv_geometry.h, head frame), pose.json (the head frame to the stage's, the scale, the jaw's turn and the model's
// coefficients), metrics.json; run.json at the root.
struct FitJob {
  std::string take_dir;
  // Frames [first_frame, last_frame); last_frame < 0: up to the last one the surfaces hold without a gap.
  int64_t first_frame = 0;
  int64_t last_frame = -1;
  // The surfaces: multi-view stereo's meshes (the default), or a directory of frame-NNNNNN/mesh.obj (ground_truth on
  // a simulated take). kNone is refused.
  GeometrySpec surface;
  // The template: FILE.obj with FILE.json beside it; empty: the shipped one.
  std::string template_obj;
  // Where the results go; empty: <take_dir>/derived/fit.
  std::string output_dir;
  GeometryMapOptions map;
  TemplateFitOptions options;
};

absl::StatusOr<JobResult> RunFit(const FitJob& job, const std::function<void(const JobProgress&)>& progress = {},
                                 const std::function<bool()>& cancelled = {});

}  // namespace stage::processing
