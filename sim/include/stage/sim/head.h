// The procedural human head: a closed triangle mesh in millimetres (forehead, brows, eye sockets with eyeballs, nose,
// cheeks, lips, chin, ears), an expression rig of linear blendshapes, a performance script of keyframed expressions
// and head motion, and skin materials as UV maps (albedo with pores and freckles, specular intensity, roughness, and
// a detail height field for pores and for the wrinkles an expression brings). Head frame: +y up, +z the way the face
// looks, +x the performer's left; the origin is the head's centre, which a performance moves and turns.
#pragma once

#include <Eigen/Core>
#include <array>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/sim/mesh.h"

namespace stage::sim {

inline constexpr int kExpressionCount = 8;
// "jaw_open", "smile_left", "smile_right", "blink_left", "blink_right", "brow_raise", "frown", "pucker".
const char* ExpressionName(int index);
// Index of an expression name, or -1.
int ExpressionIndex(const std::string& name);

struct HeadPose {
  // Expression weights in [0, 1], by ExpressionIndex.
  std::array<float, kExpressionCount> expression{};
  // Head rotation in degrees: yaw (about +y), pitch (about +x), roll (about +z), applied in that order about the neck
  // pivot; then the translation, mm.
  Eigen::Vector3f rotation_deg = Eigen::Vector3f::Zero();
  Eigen::Vector3f translation_mm = Eigen::Vector3f::Zero();
};

// Keyframes of expression and motion; between keys the pose eases (smoothstep) from one to the next.
struct Performance {
  std::vector<std::pair<double, HeadPose>> keys;  // by time, seconds
  // The pose at `t_s` (held before the first key and after the last).
  HeadPose At(double t_s) const;
  // The shipped script: 4 s through every expression and a turn of the head each way.
  static Performance Default();
  // A YAML file: `keys: [{t: 0.5, jaw_open: 0.8, yaw: 10, pitch: -5, roll: 0, x: 0, y: 0, z: 0}, ...]`.
  // Errors name the file and key.
  static absl::StatusOr<Performance> FromYaml(const std::string& path);
};

class HeadModel {
 public:
  // The procedural head; `seed` varies the skin detail; `resolution` columns around the head (rows are half that).
  static std::shared_ptr<const HeadModel> Procedural(uint64_t seed, int resolution = 256);

  // The mesh in `pose`, as a subject whose skin shows the expression's wrinkles.
  std::unique_ptr<MeshSubject> Posed(const HeadPose& pose) const;
  // The posed mesh only (for ground truth).
  TriangleMesh PosedMesh(const HeadPose& pose) const;
  // The skin (part 0) or eye (part 1) at `uv` under `expression`.
  SurfaceSample Surface(const Eigen::Vector2f& uv, int part, const std::array<float, kExpressionCount>& expr) const;

  const TriangleMesh& neutral() const { return neutral_; }

 private:
  HeadModel() = default;
  float Height(const Eigen::Vector2f& uv, const std::array<float, kExpressionCount>& expr) const;
  TriangleMesh neutral_;
  // Per expression, per vertex displacement at weight 1.
  std::array<std::vector<Eigen::Vector3f>, kExpressionCount> deltas_;
  uint64_t seed_ = 1;
};

}  // namespace stage::sim
