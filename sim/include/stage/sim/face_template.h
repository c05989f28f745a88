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

struct FaceTemplateData {
  TriangleMesh mesh;                    // neutral, head frame, mm; its uvs the template's own layout, [0, 1]^2
  std::vector<TemplateRegion> regions;  // per vertex
  std::vector<int32_t> head_vertex;     // per vertex, the head's vertex it was (not written)
  // The jaw: per vertex how far it follows the jaw's turn (0 to 1), and the axis it turns about (head frame, mm).
  std::vector<float> jaw_weight;
  Eigen::Vector3f jaw_hinge_mm = Eigen::Vector3f::Zero(), jaw_axis = Eigen::Vector3f::UnitX();
  // The template's square in the head's skin layout: uv_template = (uv_head - lo) / (hi - lo).
  float u_lo = 0, u_hi = 1, v_lo = 0, v_hi = 1;
};

// The template from the procedural head `head`: its skin triangles inside the window, at its resolution (the shipped
// template: HeadModel::Procedural(1, 256), the shipped head).
FaceTemplateData MakeFaceTemplate(const HeadModel& head);

// Writes DIR/face-template.obj and DIR/face-template.json (the layout window, the regions, where it came from).
absl::Status WriteFaceTemplate(const FaceTemplateData& data, const std::string& dir);

}  // namespace stage::sim
