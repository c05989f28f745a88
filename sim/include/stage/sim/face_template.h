// The face template processing fits to every frame (docs/assets.md), made from the shipped procedural head: the face
// cut from its skin's layout (the front of the head from below the chin to the forehead, ear to ear but for the ears)
// and laid out on a square of its own, with the regions a fit treats apart (the eyes' openings, the mouth's).
// processing/data/face-template.{obj,json} are this function's output (`stage-sim --export-face-template DIR`);
// FaceTemplateSimTest checks that they still are.
#pragma once

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "stage/common/mesh.h"
#include "stage/sim/head.h"

namespace stage::sim {

// Per template vertex: what part of the face it is on (the values of processing's FaceRegion).
enum class TemplateRegion : uint8_t { kSkin = 0, kEye = 1, kMouth = 2 };

// A low-dimensional shape and expression model over the template's vertices (head frame, mm; docs/assets.md#the-model):
// the directions in which performers' neutral faces differ from the template (principal components of the faces of
// performers drawn about the shipped head, each scaled to one standard deviation) and the shipped head's expression
// blendshapes (per vertex, the displacement at weight 1). Empty: the template has no model.
struct FaceModelData {
  std::vector<std::vector<Eigen::Vector3f>> identity;    // per component, per template vertex
  std::vector<double> identity_variance_share;           // per component, its share of the drawn faces' variance
  std::vector<std::vector<Eigen::Vector3f>> expression;  // per expression (ExpressionName order), per template vertex
  uint64_t first_identity = 0;                           // the drawn performers: identities first_identity..+count-1
  int identities = 0;
};

struct FaceTemplateData {
  TriangleMesh mesh;                    // neutral, head frame, mm; its uvs the template's own layout, [0, 1]^2
  std::vector<TemplateRegion> regions;  // per vertex
  std::vector<int32_t> head_vertex;     // per vertex, the head's vertex it was (not written)
  // The jaw: per vertex how far it follows the jaw's turn (0 to 1), and the axis it turns about (head frame, mm).
  std::vector<float> jaw_weight;
  Eigen::Vector3f jaw_hinge_mm = Eigen::Vector3f::Zero(), jaw_axis = Eigen::Vector3f::UnitX();
  // The template's square in the head's skin layout: uv_template = (uv_head - lo) / (hi - lo).
  float u_lo = 0, u_hi = 1, v_lo = 0, v_hi = 1;
  FaceModelData model;
};

// The template from the procedural head `head`: its skin triangles inside the window, at its resolution (the shipped
// template: HeadModel::Procedural(1, 256), the shipped head).
FaceTemplateData MakeFaceTemplate(const HeadModel& head);

// The model of `face` (made from the shipped head at `resolution`): the principal components of the neutral faces
// of `identities` performers (HeadShape::Drawn of first_identity onwards; keep them apart from the performers a test
// fits), as many as hold `variance_kept` of their variance, at most `max_components`; and the head's blendshapes.
// An empty model when there is nothing to draw (identities or max_components < 1) or `head` is not at `resolution`.
// The shipped model's performers (processing/data/face-model.f32): identities 1000 to 1063, none a test's performer.
inline constexpr uint64_t kFaceModelFirstIdentity = 1000;
inline constexpr int kFaceModelIdentities = 64;
FaceModelData MakeFaceModel(const FaceTemplateData& face, const HeadModel& head, uint64_t first_identity,
                            int identities, int max_components = 16, double variance_kept = 0.9999,
                            int resolution = 256);

// Writes DIR/face-template.obj and DIR/face-template.json (the layout window, the regions, where it came from), and
// with a model DIR/face-model.f32 (little-endian float32: the identity components, then the expressions, each
// vertex by vertex x, y, z), which the JSON's "model" describes.
absl::Status WriteFaceTemplate(const FaceTemplateData& data, const std::string& dir);

}  // namespace stage::sim
