// The procedural human head: a closed triangle mesh in millimetres (forehead, brows, eye sockets with eyeballs, nose,
// cheeks, lips, chin, ears), an expression rig of linear blendshapes, a performance script of keyframed expressions
// and head motion, and skin materials as UV maps (albedo with pores and freckles, specular intensity, roughness, and
// a detail height field for pores and for the wrinkles an expression brings), or a user's head loaded from OBJ
// blendshapes and texture images. Head frame: +y up, +z the way the face
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

// The rotation of `pose` (yaw, then pitch, then roll).
Eigen::Matrix3f PoseRotation(const HeadPose& pose);

// Keyframes of expression and motion; between keys the pose eases (smoothstep) from one to the next.
struct Performance {
  std::vector<std::pair<double, HeadPose>> keys;  // by time, seconds
  // Named stretches of the performance (an expression sequence: "smile-2"), by start time; each lasts until the next
  // begins. Empty: the performance is not divided.
  std::vector<std::pair<double, std::string>> sequences;
  // The pose at `t_s` (held before the first key and after the last).
  HeadPose At(double t_s) const;
  // The sequence `t_s` falls in ("" before the first, or when there are none).
  std::string SequenceAt(double t_s) const;
  // The shipped script: 4 s through every expression and a turn of the head each way.
  static Performance Default();
  // A range-of-motion session of `seconds` (the rig's "range_of_motion": 180 s), drawn from `seed`: sequences of
  // about 6 s, each working one group of expressions (jaw, smile, blink, brows, frown, pucker, asymmetric, speech;
  // every group in turn, in a drawn order, round after round) at drawn weights, named "<group>-<round>", while the
  // head turns (yaw +-30, pitch +-12, roll +-6 degrees) and moves (+-12 mm) slowly throughout. What a neural asset
  // trains on (docs/asset.md).
  static Performance RangeOfMotion(uint64_t seed, double seconds);
  // A YAML file: `keys: [{t: 0.5, jaw_open: 0.8, yaw: 10, pitch: -5, roll: 0, x: 0, y: 0, z: 0}, ...]`; a key may
  // start a named sequence (`sequence: smile-1`). Errors name the file and key.
  static absl::StatusOr<Performance> FromYaml(const std::string& path);
};

// A subject a performance poses: a mesh with per-expression blendshapes, turned about a pivot and moved, and its
// surface (material and detail normals over the texture). The head and the calibration board are such models.
class RiggedModel {
 public:
  virtual ~RiggedModel() = default;
  // The mesh in `pose`: blendshapes weighted by the expression, turned about the pivot, then translated.
  TriangleMesh PosedMesh(const HeadPose& pose) const;
  // That mesh as a subject with this model's surface.
  std::unique_ptr<MeshSubject> Posed(const HeadPose& pose) const;
  // The surface of part `part` at `uv` under `expression`. Thread-safe.
  virtual SurfaceSample Surface(const Eigen::Vector2f& uv, int part,
                                const std::array<float, kExpressionCount>& expression) const = 0;
  // True if no part of a pose can shadow another (Subject::Convex): the board's plate, not a head.
  virtual bool Convex() const { return false; }

  const TriangleMesh& neutral() const { return neutral_; }
  // True if expression `index` moves the mesh.
  bool HasBlendshape(int index) const { return !deltas_[static_cast<size_t>(index)].empty(); }
  const Eigen::Vector3f& pivot() const { return pivot_; }

 protected:
  TriangleMesh neutral_;
  // Per expression, per vertex displacement at weight 1 (empty: the expression does not move the mesh).
  std::array<std::vector<Eigen::Vector3f>, kExpressionCount> deltas_;
  Eigen::Vector3f pivot_ = Eigen::Vector3f::Zero();
};

// A user's head from files (rig: sim.subject.asset); paths already resolved.
struct HeadAssetFiles {
  std::string neutral_obj;
  // Expression name -> OBJ.
  std::vector<std::pair<std::string, std::string>> blendshapes;
  std::string albedo, specular, roughness, normal;
  // Where the images are missing: the subject's specular intensity and roughness.
  float specular_value = 0.03f, roughness_value = 0.3f;
  float specular_scale = 0.1f;
  float units_mm = 1;
  Eigen::Vector3f pivot_mm{0, -95, -15};
};

// Where the procedural head's features sit in its skin's layout, as azimuth (from +z towards +x) and elevation in
// radians (u = azimuth / 2 pi + 1/2, v = elevation / pi + 1/2): for tools that mark regions of the face.
struct HeadLandmarks {
  float eye_azimuth;  // each eye at plus and minus this
  float eye_elevation;
  float mouth_elevation;  // the mouth line, centred at azimuth 0
  // The axis the jaw turns about (the jaw's hinges), head frame, mm: a point on it and its direction.
  Eigen::Vector3f jaw_hinge_mm, jaw_axis;
};
HeadLandmarks ProceduralHeadLandmarks();

// The proportions of the procedural head: one performer's face. Identity 0 is the shipped head (the one processing's
// face template is made from, docs/assets.md); any other identity draws a performer about it.
struct HeadShape {
  float width_mm = 76, height_mm = 112, depth_mm = 98;  // the skull's semi-axes (x, y, z)
  float jaw = 0.14f;                                    // how much the jaw narrows below the cheekbones
  // Heights of the face's features over the skull, mm.
  float nose_mm = 26, nose_tip_mm = 7, nostrils_mm = 5, eye_sockets_mm = 13, brows_mm = 6, cheekbones_mm = 8,
        lips_mm = 8, chin_mm = 10, ears_mm = 20;

  // Identity 0: the defaults above; another: the skull's axes varied by 4 % and the jaw and every feature by 20 %
  // (standard deviations, clamped at 2.5), drawn from the identity.
  static HeadShape Drawn(uint64_t identity);
};

class HeadModel final : public RiggedModel {
 public:
  // The procedural head; `seed` varies the skin detail; `resolution` columns around the head (rows are half that);
  // `shape` its proportions; `blood_flow` (0..1) how much its skin flushes where an expression works it.
  static std::shared_ptr<const HeadModel> Procedural(uint64_t seed, int resolution = 256, const HeadShape& shape = {},
                                                     float blood_flow = 0);
  // A user's head: errors name the file (and line, or the expression) at fault.
  static absl::StatusOr<std::shared_ptr<const HeadModel>> FromAsset(const HeadAssetFiles& files);

  // The skin (part 0) or eye (part 1) at `uv` under `expression`; a loaded head samples its images.
  SurfaceSample Surface(const Eigen::Vector2f& uv, int part,
                        const std::array<float, kExpressionCount>& expression) const override;

  // The images of a loaded head (RGB(A) floats, row 0 at v = 1), or none.
  struct Maps;
  // Where a loaded head's decoded images are: the shared cache file every process of the stage maps (its path), or
  // "decoded" (this process's own copy); empty for the procedural head.
  const std::string& maps_origin() const { return maps_origin_; }
  // What a loaded mesh lacks or has that the simulator does not render, in words: its holes (where the cameras see
  // through it), transparent materials left out. Empty for a closed, opaque mesh.
  const std::vector<std::string>& notes() const { return notes_; }

 private:
  HeadModel() = default;
  float Height(const Eigen::Vector2f& uv, const std::array<float, kExpressionCount>& expr) const;
  uint64_t seed_ = 1;
  float blood_flow_ = 0;
  std::shared_ptr<const Maps> maps_;  // a loaded head's images
  std::string maps_origin_;
  std::vector<std::string> notes_;
};

}  // namespace stage::sim
