// The face template every frame's fit starts from (docs/assets.md): a neutral face mesh in the head frame (mm) with
// its own UV layout, and the regions a fit treats apart. The shipped one is compiled in (processing/data/: the
// simulator's shipped head's face, made by `stage-sim --export-face-template`); another is read from files.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/mesh.h"

namespace stage::processing {

enum class FaceRegion : uint8_t {
  kSkin = 0,
  kEye = 1,    // the eyes' openings: the lids over the eyeballs, which the template does not hold
  kMouth = 2,  // the mouth's opening: the lips' inner edges, which the jaw parts
};

struct FaceTemplate {
  TriangleMesh mesh;                // neutral, head frame, mm; uvs in [0, 1]^2
  std::vector<FaceRegion> regions;  // per vertex
  // The template's square in the simulator's head layout (uv_head = lo + uv * (hi - lo)), for evaluation against
  // the simulator's truth, whose meshes carry that layout.
  Eigen::Vector2f head_layout_lo = Eigen::Vector2f::Zero(), head_layout_hi = Eigen::Vector2f::Ones();
  std::string source;
  // The jaw (none when the template has no "jaw"): per vertex how far it follows the jaw's turn (0 to 1), and the axis
  // the jaw turns about, head frame, mm.
  std::vector<float> jaw_weight;
  Eigen::Vector3f jaw_hinge = Eigen::Vector3f::Zero(), jaw_axis = Eigen::Vector3f::UnitX();
  // The shape and expression model (empty when the template has none; docs/assets.md#the-model): per vertex, head
  // frame, mm. identity_basis: the directions performers' faces differ from the template in, each at one standard
  // deviation (a fit's coefficients are in standard deviations); expression_basis: blendshapes, each the
  // displacement at weight 1, named by expression_names.
  std::vector<std::vector<Eigen::Vector3f>> identity_basis, expression_basis;
  std::vector<std::string> expression_names;

  Eigen::Vector2f HeadLayoutUv(const Eigen::Vector2f& uv) const {
    return head_layout_lo + uv.cwiseProduct(head_layout_hi - head_layout_lo);
  }
};

// A template from FILE.obj and FILE.json beside it. Errors name the file and field.
absl::StatusOr<FaceTemplate> LoadFaceTemplate(const std::string& obj_path);
// The template compiled into the program (processing/data/face-template.{obj,json}).
absl::StatusOr<FaceTemplate> ShippedFaceTemplate();

}  // namespace stage::processing
