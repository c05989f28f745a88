#include "stage/processing/template_fit.h"

#include <Eigen/Cholesky>
#include <Eigen/Sparse>
#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>
#include <unordered_map>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/evaluate_mvs.h"
#include "stage/processing/uv_geometry.h"
#include "statistics.h"

namespace stage::processing {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Per template vertex: the nearest point of the surface, or none (too far, or the surface turned away).
struct Correspondences {
  std::vector<Eigen::Vector3f> points, normals;
  std::vector<uint8_t> valid;
  int64_t count = 0;
  double rms_mm = 0;
};

std::vector<Eigen::Vector3f> TriangleNormals(const TriangleMesh& m) {
  std::vector<Eigen::Vector3f> n(m.triangles.size());
  for (size_t k = 0; k < n.size(); ++k) {
    const auto& t = m.triangles[k];
    n[k] = (m.positions[t[1]] - m.positions[t[0]]).cross(m.positions[t[2]] - m.positions[t[0]]).normalized();
  }
  return n;
}

// The surface as the fit sees it: its nearest points, its triangles' normals, and the triangles with a vertex on its
// border (an edge of one triangle only: a hole's rim or the mesh's edge), whose nearest points are no evidence of
// where the skin is (a vertex over a hole finds the hole's rim and would be drawn to it).
struct Target {
  explicit Target(const TriangleMesh& surface) : nearest(surface), normals(TriangleNormals(surface)) {
    // Vertices at the same place are one (an OBJ splits them at texture seams, which are no border).
    std::map<std::array<float, 3>, int32_t> first;
    std::vector<int32_t> welded(surface.positions.size());
    for (size_t v = 0; v < welded.size(); ++v) {
      const Eigen::Vector3f& p = surface.positions[v];
      welded[v] = first.try_emplace({p.x(), p.y(), p.z()}, static_cast<int32_t>(v)).first->second;
    }
    std::unordered_map<uint64_t, int> edges;
    auto key = [](int32_t a, int32_t b) {
      return (static_cast<uint64_t>(static_cast<uint32_t>(std::min(a, b))) << 32) |
             static_cast<uint32_t>(std::max(a, b));
    };
    for (const auto& t : surface.triangles) {
      for (int k = 0; k < 3; ++k) ++edges[key(welded[t[k]], welded[t[(k + 1) % 3]])];
    }
    std::vector<uint8_t> on_border(surface.positions.size(), 0);
    for (const auto& [edge, count] : edges) {
      if (count != 1) continue;
      on_border[edge >> 32] = 1;
      on_border[edge & 0xffffffffu] = 1;
    }
    border.resize(surface.triangles.size());
    for (size_t k = 0; k < border.size(); ++k) {
      const auto& t = surface.triangles[k];
      border[k] = on_border[static_cast<size_t>(welded[t[0]])] | on_border[static_cast<size_t>(welded[t[1]])] |
                  on_border[static_cast<size_t>(welded[t[2]])];
    }
  }
  SurfaceDistance nearest;
  std::vector<Eigen::Vector3f> normals;
  std::vector<uint8_t> border;
};

// The surface's nearest points to `positions`; only where `use`, the surface's normal lies within the options'
// angle of the template's (either winding: an OBJ does not say which side is out) and, with the options'
// skip_border, the nearest point is not on a triangle at the surface's border.
Correspondences Match(const std::vector<Eigen::Vector3f>& positions, const std::vector<uint8_t>& use,
                      const FaceTemplate& face, const Target& target, const TemplateFitOptions& options) {
  Correspondences c;
  c.points.resize(positions.size());
  c.normals.resize(positions.size());
  c.valid.assign(positions.size(), 0);
  const std::vector<Eigen::Vector3f> normals = VertexNormals(positions, face.mesh.triangles);
  const float cos_max = static_cast<float>(std::cos(options.max_normal_angle_deg * kPi / 180));
  double sum = 0;
  for (size_t i = 0; i < positions.size(); ++i) {
    if (!use[i]) continue;
    int32_t triangle = -1;
    const Eigen::Vector3f q = target.nearest.Closest(positions[i], &triangle);
    if (triangle < 0 || (options.skip_border && target.border[static_cast<size_t>(triangle)])) continue;
    const float d = (q - positions[i]).norm();
    const Eigen::Vector3f& n = target.normals[static_cast<size_t>(triangle)];
    if (d > options.max_distance_mm || std::abs(n.dot(normals[i])) < cos_max) continue;
    c.points[i] = q;
    c.normals[i] = n;
    c.valid[i] = 1;
    ++c.count;
    sum += static_cast<double>(d) * d;
  }
  c.rms_mm = c.count > 0 ? std::sqrt(sum / static_cast<double>(c.count)) : 0;
  return c;
}

// One Gauss-Newton step of point-to-plane ICP over a rigid motion, a uniform scale about the head's origin (with
// `fit_scale`: a performer's head is not the template's size) and the jaw's turn about its hinge (the template's jaw
// weights; the jaw moves the lower face along the surface, where a nearest-point term alone would leave it): the
// small motion that best moves the matched vertices onto their tangent planes. A scale per axis was tried: it takes
// up the features' heights too (a smaller nose as a flatter head) and turned every vertex's direction from the head's
// centre, sliding the fit 8.4 mm against 5.1 (docs/assets.md).
// `p` turned by `weight` x `angle_rad` about the axis through `hinge` (the jaw's turn of one vertex).
Eigen::Vector3f TurnJaw(const Eigen::Vector3f& p, const Eigen::Vector3f& hinge, const Eigen::Vector3f& axis,
                        float weight, float angle_rad) {
  return weight > 0 ? Eigen::Vector3f(hinge + Eigen::AngleAxisf(weight * angle_rad, axis) * (p - hinge)) : p;
}

struct Placement {
  Eigen::Vector3f origin, hinge, axis;  // stage frame: the head's origin, the jaw's hinge and axis
  const std::vector<float>* jaw_weight;
};
struct PlacementStep {
  Eigen::Isometry3f rigid = Eigen::Isometry3f::Identity();
  float scale = 1, jaw_rad = 0;

  // `p` (vertex `i`) moved by the step: the jaw's turn, the scale, then the rigid motion.
  Eigen::Vector3f Apply(const Placement& at, size_t i, const Eigen::Vector3f& p) const {
    const Eigen::Vector3f jawed = TurnJaw(p, at.hinge, at.axis, (*at.jaw_weight)[i], jaw_rad);
    return rigid * (at.origin + scale * (jawed - at.origin));
  }
};
PlacementStep PlacementGaussNewton(const std::vector<Eigen::Vector3f>& positions, const Correspondences& c,
                                   const Placement& at, bool fit_scale) {
  constexpr int kN = 8;
  Eigen::Matrix<double, kN, kN> ata = Eigen::Matrix<double, kN, kN>::Zero();
  Eigen::Matrix<double, kN, 1> atb = Eigen::Matrix<double, kN, 1>::Zero();
  const Eigen::Vector3d origin = at.origin.cast<double>(), hinge = at.hinge.cast<double>(),
                        axis = at.axis.cast<double>();
  for (size_t i = 0; i < positions.size(); ++i) {
    if (!c.valid[i]) continue;
    const Eigen::Vector3d p = positions[i].cast<double>(), n = c.normals[i].cast<double>();
    const double w = (*at.jaw_weight)[i];
    Eigen::Matrix<double, kN, 1> a;
    a << p.cross(n), n, fit_scale ? n.dot(p - origin) : 0.0, w * n.dot(axis.cross(p - hinge));
    ata += a * a.transpose();
    atb += a * n.dot(c.points[i].cast<double>() - p);
  }
  for (int k : {6, 7}) {
    if (ata(k, k) < 1e-9) ata(k, k) = 1;  // a term the data does not see (no scale asked for, no jaw in the template)
  }
  const Eigen::Matrix<double, kN, 1> x = ata.ldlt().solve(atb);
  PlacementStep step;
  const Eigen::Vector3d w = x.head<3>();
  Eigen::Isometry3d rigid = Eigen::Isometry3d::Identity();
  if (w.norm() > 0) rigid.linear() = Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix();
  rigid.translation() = x.segment<3>(3);
  step.rigid = rigid.cast<float>();
  step.scale = static_cast<float>(1 + x(6));
  step.jaw_rad = static_cast<float>(x(7));
  return step;
}

// The template's face with the model's coefficients (head frame): the neutral template plus the identity and
// expression components they weight.
std::vector<Eigen::Vector3f> ModelShape(const FaceTemplate& face, const std::vector<float>& identity,
                                        const std::vector<float>& expression) {
  std::vector<Eigen::Vector3f> out = face.mesh.positions;
  auto add = [&](const std::vector<std::vector<Eigen::Vector3f>>& basis, const std::vector<float>& weights) {
    for (size_t k = 0; k < std::min(basis.size(), weights.size()); ++k) {
      if (weights[k] == 0) continue;
      for (size_t i = 0; i < out.size(); ++i) out[i] += weights[k] * basis[k][i];
    }
  };
  add(face.identity_basis, identity);
  add(face.expression_basis, expression);
  return out;
}

// `base` (the template's face, head frame) with the jaw turned by `jaw_rad`, scaled about the head's origin.
std::vector<Eigen::Vector3f> Shaped(const FaceTemplate& face, const std::vector<Eigen::Vector3f>& base, float scale,
                                    float jaw_rad) {
  std::vector<Eigen::Vector3f> out(base.size());
  for (size_t i = 0; i < out.size(); ++i) {
    const float w = face.jaw_weight.empty() ? 0.0f : face.jaw_weight[i];
    out[i] = scale * TurnJaw(base[i], face.jaw_hinge, face.jaw_axis, w, jaw_rad);
  }
  return out;
}

// The model step's unknowns, in order: the rigid motion (6), the jaw's turn (only for a template without expression
// blendshapes: with them the jaw is jaw_open's, and the two would trade), then the identity's and the expression's
// coefficients. No scale: the identity's components carry the head's size.
struct ModelLayout {
  bool jaw = false;
  size_t n_id = 0, n_ex = 0;
  Eigen::Index Id(size_t k) const { return static_cast<Eigen::Index>(6 + (jaw ? 1 : 0) + k); }
  Eigen::Index Ex(size_t k) const { return Id(n_id) + static_cast<Eigen::Index>(k); }
  Eigen::Index Size() const { return Ex(n_ex); }
};

// The model step's normal equations over the matched vertices, and the point-to-plane residuals' robust variance
// (the median squared residual of a normal distribution is 0.455 of its variance).
struct ModelSystem {
  Eigen::MatrixXd ata;
  Eigen::VectorXd atb;
  double variance = 1;
};
ModelSystem ModelEquations(const FaceTemplate& face, const Correspondences& c, const ModelLayout& layout,
                           const TemplateFit& fit) {
  ModelSystem sys{Eigen::MatrixXd::Zero(layout.Size(), layout.Size()), Eigen::VectorXd::Zero(layout.Size())};
  const Eigen::Matrix3f r = fit.stage_from_head.linear();
  const Eigen::Vector3d hinge = (fit.stage_from_head * (fit.scale * face.jaw_hinge)).cast<double>(),
                        axis = (r * face.jaw_axis).cast<double>();
  Eigen::VectorXd a(layout.Size());
  std::vector<double> squared;
  squared.reserve(static_cast<size_t>(c.count));
  for (size_t i = 0; i < c.valid.size(); ++i) {
    if (!c.valid[i]) continue;
    const Eigen::Vector3d p = fit.positions[i].cast<double>(), nrm = c.normals[i].cast<double>();
    const float w = face.jaw_weight.empty() ? 0.0f : face.jaw_weight[i];
    a.head<3>() = p.cross(nrm);
    a.segment<3>(3) = nrm;
    if (layout.jaw) a(6) = w * nrm.dot(axis.cross(p - hinge));
    // A component's displacement d (head frame) moves the vertex by R s J d (J the vertex's turn with the jaw).
    const Eigen::Vector3f m =
        fit.scale * (Eigen::AngleAxisf(w * fit.jaw_rad, face.jaw_axis).inverse() * (r.transpose() * c.normals[i]));
    for (size_t k = 0; k < layout.n_id; ++k) a(layout.Id(k)) = m.dot(face.identity_basis[k][i]);
    for (size_t k = 0; k < layout.n_ex; ++k) a(layout.Ex(k)) = m.dot(face.expression_basis[k][i]);
    sys.ata.selfadjointView<Eigen::Lower>().rankUpdate(a);
    const double residual = nrm.dot(c.points[i].cast<double>() - p);
    sys.atb += a * residual;
    squared.push_back(residual * residual);
  }
  sys.ata = Eigen::MatrixXd(sys.ata.selfadjointView<Eigen::Lower>());
  if (layout.jaw && sys.ata(6, 6) < 1e-9) sys.ata(6, 6) = 1;  // no vertex follows the jaw
  if (!squared.empty()) sys.variance = Quantile(squared, 1, 2) / 0.455;
  return sys;
}

// One Gauss-Newton step of the model's fit: the pose (and the jaw, as the layout says) and the model's coefficients
// together, point to plane, each coefficient held toward 0 by its prior, which weighs as many vertices at the fit's
// typical residual (loose on a surface the model meets closely, firm on a noisy one). Updates `fit`'s coefficients,
// pose and jaw, not its positions.
void ModelStep(const FaceTemplate& face, const Correspondences& c, const TemplateFitOptions& options,
               const ModelLayout& layout, TemplateFit* fit) {
  ModelSystem sys = ModelEquations(face, c, layout, *fit);
  for (size_t k = 0; k < layout.n_id; ++k) {
    sys.ata(layout.Id(k), layout.Id(k)) += sys.variance * options.identity_prior;
    sys.atb(layout.Id(k)) -= sys.variance * options.identity_prior * fit->identity[k];
  }
  for (size_t k = 0; k < layout.n_ex; ++k) {
    sys.ata(layout.Ex(k), layout.Ex(k)) += sys.variance * options.expression_prior;
    sys.atb(layout.Ex(k)) -= sys.variance * options.expression_prior * fit->expression[k];
  }
  const Eigen::VectorXd x = sys.ata.ldlt().solve(sys.atb);
  const Eigen::Vector3d turn = x.head<3>();
  Eigen::Isometry3d rigid = Eigen::Isometry3d::Identity();
  if (turn.norm() > 0) rigid.linear() = Eigen::AngleAxisd(turn.norm(), turn.normalized()).toRotationMatrix();
  rigid.translation() = x.segment<3>(3);
  fit->stage_from_head = rigid.cast<float>() * fit->stage_from_head;
  if (layout.jaw) fit->jaw_rad += static_cast<float>(x(6));
  // Kept to where the model means something: a face within the identity's reach, blendshapes between none and full.
  const auto reach = static_cast<float>(options.identity_reach);
  for (size_t k = 0; k < layout.n_id; ++k) {
    fit->identity[k] = std::clamp(fit->identity[k] + static_cast<float>(x(layout.Id(k))), -reach, reach);
  }
  for (size_t k = 0; k < layout.n_ex; ++k) {
    fit->expression[k] = std::clamp(fit->expression[k] + static_cast<float>(x(layout.Ex(k))), 0.0f, 1.0f);
  }
}

// The rigid motion that best takes `from` onto `to` over the vertices `use` marks (Kabsch).
Eigen::Isometry3f BestRigid(const std::vector<Eigen::Vector3f>& from, const std::vector<Eigen::Vector3f>& to,
                            const std::vector<uint8_t>& use) {
  Eigen::Vector3d ca = Eigen::Vector3d::Zero(), cb = Eigen::Vector3d::Zero();
  double n = 0;
  for (size_t i = 0; i < from.size(); ++i) {
    if (!use[i]) continue;
    ca += from[i].cast<double>();
    cb += to[i].cast<double>();
    n += 1;
  }
  ca /= n;
  cb /= n;
  Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
  for (size_t i = 0; i < from.size(); ++i) {
    if (use[i]) h += (from[i].cast<double>() - ca) * (to[i].cast<double>() - cb).transpose();
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(h, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d d = Eigen::Matrix3d::Identity();
  if ((svd.matrixV() * svd.matrixU().transpose()).determinant() < 0) d(2, 2) = -1;
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = svd.matrixV() * d * svd.matrixU().transpose();
  t.translation() = cb - t.linear() * ca;
  return t.cast<float>();
}

// The template's graph Laplacian (uniform weights over its edges).
Eigen::SparseMatrix<double> Laplacian(const TriangleMesh& m) {
  std::set<std::pair<int32_t, int32_t>> edges;
  for (const auto& t : m.triangles) {
    for (int k = 0; k < 3; ++k) edges.insert(std::minmax(t[k], t[(k + 1) % 3]));
  }
  std::vector<Eigen::Triplet<double>> entries;
  std::vector<double> degree(m.positions.size(), 0);
  for (const auto& [a, b] : edges) {
    entries.emplace_back(a, b, -1);
    entries.emplace_back(b, a, -1);
    degree[static_cast<size_t>(a)] += 1;
    degree[static_cast<size_t>(b)] += 1;
  }
  for (size_t v = 0; v < degree.size(); ++v) entries.emplace_back(v, v, degree[v]);
  Eigen::SparseMatrix<double> l(static_cast<Eigen::Index>(m.positions.size()),
                                static_cast<Eigen::Index>(m.positions.size()));
  l.setFromTriplets(entries.begin(), entries.end());
  return l;
}

// Non-rigid ICP at one stiffness: argmin_y sum_i w_i |y_i - c_i|^2 + alpha sum_edges |(y_a - y_b) - (r_a - r_b)|^2,
// the rest shape r the template placed by the pose: (W + alpha L) y = W c + alpha L r, per coordinate.
absl::Status NonRigidStep(const Eigen::SparseMatrix<double>& laplacian, const std::vector<Eigen::Vector3f>& rest,
                          const Correspondences& c, double alpha, std::vector<Eigen::Vector3f>* positions) {
  const auto n = static_cast<Eigen::Index>(rest.size());
  Eigen::SparseMatrix<double> a = alpha * laplacian;
  Eigen::MatrixX3d rhs(n, 3), r(n, 3);
  for (Eigen::Index i = 0; i < n; ++i) r.row(i) = rest[static_cast<size_t>(i)].cast<double>().transpose();
  rhs = alpha * (laplacian * r);
  for (Eigen::Index i = 0; i < n; ++i) {
    if (!c.valid[static_cast<size_t>(i)]) continue;
    a.coeffRef(i, i) += 1;
    rhs.row(i) += c.points[static_cast<size_t>(i)].cast<double>().transpose();
  }
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(a);
  if (solver.info() != Eigen::Success) {
    return absl::InternalError("template fit: the non-rigid system could not be factored (no vertex near the surface)");
  }
  const Eigen::MatrixX3d y = solver.solve(rhs);
  for (Eigen::Index i = 0; i < n; ++i) (*positions)[static_cast<size_t>(i)] = y.row(i).transpose().cast<float>();
  return absl::OkStatus();
}

// Non-rigid ICP along the rest shape's normals only: y_i = r_i + d_i m_i (m the rest shape's vertex normals), the
// offsets d a membrane (alpha sum_edges (d_a - d_b)^2) over the point-to-plane data term
// sum_i (n_i . (r_i + d_i m_i - c_i))^2. The skin stays where the model put it along the surface; the surface's
// detail comes in as offsets.
absl::Status NormalStep(const Eigen::SparseMatrix<double>& laplacian, const std::vector<Eigen::Vector3f>& rest,
                        const std::vector<Eigen::Vector3f>& rest_normals, const Correspondences& c, double alpha,
                        std::vector<Eigen::Vector3f>* positions) {
  const auto n = static_cast<Eigen::Index>(rest.size());
  Eigen::SparseMatrix<double> a = alpha * laplacian;
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(n);
  for (Eigen::Index i = 0; i < n; ++i) {
    const auto k = static_cast<size_t>(i);
    // A vertex off every correspondence's component (none in its part of the mesh) stays at its rest.
    a.coeffRef(i, i) += 1e-9;
    if (!c.valid[k]) continue;
    const double w = c.normals[k].dot(rest_normals[k]);
    a.coeffRef(i, i) += w * w;
    rhs(i) += w * c.normals[k].dot(c.points[k] - rest[k]);
  }
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(a);
  if (solver.info() != Eigen::Success) {
    return absl::InternalError("template fit: the non-rigid system could not be factored (no vertex near the surface)");
  }
  const Eigen::VectorXd d = solver.solve(rhs);
  for (Eigen::Index i = 0; i < n; ++i) {
    const auto k = static_cast<size_t>(i);
    (*positions)[k] = rest[k] + static_cast<float>(d(i)) * rest_normals[k];
  }
  return absl::OkStatus();
}

}  // namespace

const char* NonRigidMotionName(NonRigidMotion m) {
  switch (m) {
    case NonRigidMotion::kAuto:
      return "auto";
    case NonRigidMotion::kFree:
      return "free";
    case NonRigidMotion::kAlongNormal:
      return "along_normal";
  }
  return "?";
}

absl::StatusOr<NonRigidMotion> ParseNonRigidMotion(const std::string& name) {
  for (NonRigidMotion m : {NonRigidMotion::kAuto, NonRigidMotion::kFree, NonRigidMotion::kAlongNormal}) {
    if (name == NonRigidMotionName(m)) return m;
  }
  return absl::InvalidArgumentError(
      absl::StrCat("template fit: non-rigid motion \"", name, "\" is not auto, free or along_normal"));
}

absl::Status TemplateFitOptions::Validate() const {
  if (rigid_iterations < 0 || rigid_iterations > 1000) {
    return absl::InvalidArgumentError(
        absl::StrCat("template fit: rigid_iterations ", rigid_iterations, " not in 0..1000"));
  }
  for (double s : stiffness) {
    if (!(s > 0)) return absl::InvalidArgumentError(absl::StrCat("template fit: stiffness ", s, " is not > 0"));
  }
  if (iterations_per_stage < 1 || iterations_per_stage > 100) {
    return absl::InvalidArgumentError(
        absl::StrCat("template fit: iterations_per_stage ", iterations_per_stage, " not in 1..100"));
  }
  if (!(max_distance_mm > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("template fit: max_distance_mm ", max_distance_mm, " is not > 0"));
  }
  if (!(max_normal_angle_deg > 0 && max_normal_angle_deg <= 180)) {
    return absl::InvalidArgumentError(
        absl::StrCat("template fit: max_normal_angle_deg ", max_normal_angle_deg, " not in (0, 180]"));
  }
  if (model_iterations < 0 || model_iterations > 1000) {
    return absl::InvalidArgumentError(
        absl::StrCat("template fit: model_iterations ", model_iterations, " not in 0..1000"));
  }
  if (!(identity_reach > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("template fit: identity_reach ", identity_reach, " is not > 0"));
  }
  if (!(identity_prior >= 0) || !(expression_prior >= 0)) {
    return absl::InvalidArgumentError(absl::StrCat("template fit: identity_prior ", identity_prior,
                                                   " and expression_prior ", expression_prior, " must be >= 0"));
  }
  return absl::OkStatus();
}

TemplateFit StartAt(const FaceTemplate& face, const Eigen::Isometry3f& stage_from_head) {
  TemplateFit fit;
  fit.stage_from_head = stage_from_head;
  fit.positions.reserve(face.mesh.positions.size());
  for (const auto& p : face.mesh.positions) fit.positions.push_back(stage_from_head * p);
  return fit;
}

namespace {

// What a fit of `face` fits, beside the pose: the scale (asked for, and no identity model fitted: its components carry
// the head's size, and a free scale traded with them from frame to frame), the jaw's turn (no expression blendshapes
// fitted: jaw_open is the jaw then), the model.
struct FitTerms {
  bool scale = false, jaw = false, model = false;
};
FitTerms TermsOf(const FaceTemplate& face, const TemplateFitOptions& options) {
  FitTerms t;
  t.model = options.model_iterations > 0 && (!face.identity_basis.empty() || !face.expression_basis.empty());
  t.scale = options.fit_scale && !(t.model && !face.identity_basis.empty());
  t.jaw = !face.jaw_weight.empty() && !(t.model && !face.expression_basis.empty());
  return t;
}

// The placement: point-to-plane ICP over the rigid motion, and the scale and the jaw's turn as `terms` say.
void Place(const FaceTemplate& face, const Target& target, const std::vector<uint8_t>& skin,
           const TemplateFitOptions& options, const FitTerms& terms, TemplateFit* fit) {
  const std::vector<float> no_jaw(face.mesh.positions.size(), 0.0f);
  for (int it = 0; it < options.rigid_iterations; ++it) {
    const Correspondences c = Match(fit->positions, skin, face, target, options);
    if (c.count < 9) break;
    const Placement at{fit->stage_from_head.translation(), fit->stage_from_head * (fit->scale * face.jaw_hinge),
                       fit->stage_from_head.linear() * face.jaw_axis, terms.jaw ? &face.jaw_weight : &no_jaw};
    const PlacementStep step = PlacementGaussNewton(fit->positions, c, at, terms.scale);
    for (size_t i = 0; i < fit->positions.size(); ++i) fit->positions[i] = step.Apply(at, i, fit->positions[i]);
    fit->stage_from_head = step.rigid * fit->stage_from_head;
    fit->scale *= step.scale;
    fit->jaw_rad += step.jaw_rad;
    if (step.rigid.translation().norm() < 1e-4f && Eigen::AngleAxisf(step.rigid.linear()).angle() < 1e-6f &&
        std::abs(step.scale - 1) < 1e-6f && std::abs(step.jaw_rad) < 1e-6f) {
      break;
    }
  }
}

// The template's face as the model's coefficients, the scale and the jaw shape it (head frame).
std::vector<Eigen::Vector3f> RestShape(const FaceTemplate& face, const TemplateFit& fit) {
  return Shaped(face, ModelShape(face, fit.identity, fit.expression), fit.scale, fit.jaw_rad);
}

// `fit`'s positions: its rest shape, posed.
void PoseRestShape(const FaceTemplate& face, TemplateFit* fit) {
  const std::vector<Eigen::Vector3f> shaped = RestShape(face, *fit);
  for (size_t i = 0; i < shaped.size(); ++i) fit->positions[i] = fit->stage_from_head * shaped[i];
}

// The model's fit (coefficients carried from the frame before, the template's neutral face on a first frame).
void FitModel(const FaceTemplate& face, const Target& target, const std::vector<uint8_t>& skin,
              const TemplateFitOptions& options, const FitTerms& terms, TemplateFit* fit) {
  fit->identity.resize(face.identity_basis.size(), 0.0f);
  fit->expression.resize(face.expression_basis.size(), 0.0f);
  // From the model's own shape, not the frame before's non-rigid detail.
  PoseRestShape(face, fit);
  const ModelLayout layout{terms.jaw, face.identity_basis.size(), face.expression_basis.size()};
  for (int it = 0; it < options.model_iterations; ++it) {
    const Correspondences c = Match(fit->positions, skin, face, target, options);
    if (c.count < 9) break;
    ModelStep(face, c, options, layout, fit);
    PoseRestShape(face, fit);
  }
}

// The non-rigid stages, from the rest shape `shaped` (head frame): along its normals or freely.
absl::Status FitNonRigid(const FaceTemplate& face, const Target& target, const std::vector<uint8_t>& skin,
                         const TemplateFitOptions& options, bool along_normal,
                         const std::vector<Eigen::Vector3f>& shaped, TemplateFit* fit) {
  const Eigen::SparseMatrix<double> laplacian = Laplacian(face.mesh);
  for (double alpha : options.stiffness) {
    std::vector<Eigen::Vector3f> rest(face.mesh.positions.size());
    for (size_t i = 0; i < rest.size(); ++i) rest[i] = fit->stage_from_head * shaped[i];
    const std::vector<Eigen::Vector3f> rest_normals =
        along_normal ? VertexNormals(rest, face.mesh.triangles) : std::vector<Eigen::Vector3f>{};
    for (int it = 0; it < options.iterations_per_stage; ++it) {
      const Correspondences c = Match(fit->positions, skin, face, target, options);
      if (c.count == 0) {
        return absl::NotFoundError(absl::StrCat("template fit: no template vertex within ", options.max_distance_mm,
                                                " mm of the surface (is the start's pose right?)"));
      }
      STAGE_RETURN_IF_ERROR(along_normal ? NormalStep(laplacian, rest, rest_normals, c, alpha, &fit->positions)
                                         : NonRigidStep(laplacian, rest, c, alpha, &fit->positions));
    }
    // The head's pose follows the shape: the rigid motion that best places the rest shape on it.
    fit->stage_from_head = BestRigid(shaped, fit->positions, skin);
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<TemplateFit> FitTemplate(const FaceTemplate& face, const TriangleMesh& surface, const TemplateFit& start,
                                        const TemplateFitOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (surface.triangles.empty()) return absl::InvalidArgumentError("template fit: the surface has no triangles");
  if (start.positions.size() != face.mesh.positions.size()) {
    return absl::InvalidArgumentError(absl::StrCat("template fit: the start has ", start.positions.size(),
                                                   " vertices, the template ", face.mesh.positions.size()));
  }
  const Target target(surface);
  // The data term holds on the skin; the eyes' and mouth's openings follow their neighbours.
  std::vector<uint8_t> skin(face.regions.size());
  for (size_t i = 0; i < skin.size(); ++i) skin[i] = face.regions[i] == FaceRegion::kSkin ? 1 : 0;
  const FitTerms terms = TermsOf(face, options);
  TemplateFit fit = start;
  if (!terms.model) {
    fit.identity.clear();
    fit.expression.clear();
  }
  Place(face, target, skin, options, terms, &fit);
  if (terms.model) FitModel(face, target, skin, options, terms, &fit);
  const bool along_normal =
      options.nonrigid == NonRigidMotion::kAlongNormal || (options.nonrigid == NonRigidMotion::kAuto && terms.model);
  STAGE_RETURN_IF_ERROR(FitNonRigid(face, target, skin, options, along_normal, RestShape(face, fit), &fit));
  const Correspondences last = Match(fit.positions, skin, face, target, options);
  fit.rms_mm = last.rms_mm;
  fit.matched = last.count;
  return fit;
}

absl::StatusOr<TriangleMesh> TemplateOnTruth(const FaceTemplate& face, const TriangleMesh& truth) {
  STAGE_ASSIGN_OR_RETURN(const GeometryMap map, MakeGeometryMap(truth, Eigen::Isometry3f::Identity(), {.size = 2048}));
  TriangleMesh placed = face.mesh;
  for (size_t v = 0; v < placed.positions.size(); ++v) {
    const std::optional<Eigen::Vector3f> p = SampleGeometryMap(map, face.HeadLayoutUv(placed.uvs[v]));
    if (!p) {
      return absl::InvalidArgumentError(
          absl::StrCat("template on truth: the truth's layout does not cover template vertex ", v));
    }
    placed.positions[v] = *p;
  }
  return placed;
}

absl::StatusOr<FitEvaluation> EvaluateFit(const FaceTemplate& face, const TemplateFit& fit, const TriangleMesh& truth) {
  if (fit.positions.size() != face.mesh.positions.size()) {
    return absl::InvalidArgumentError("evaluate fit: the fit is not of this template");
  }
  // The truth's surface over its UV layout, finely (a texel of 2048 is ~0.3 mm on the head), stage frame.
  constexpr int kSize = 2048;
  STAGE_ASSIGN_OR_RETURN(const GeometryMap map,
                         MakeGeometryMap(truth, Eigen::Isometry3f::Identity(), {.size = kSize, .dilation_px = 2}));
  struct Errors {
    std::vector<float> full, sliding;
    double sum2 = 0, normal2 = 0, sliding2 = 0;
  } by_region[3];
  const float du = 1.0f / kSize;
  for (size_t i = 0; i < fit.positions.size(); ++i) {
    const Eigen::Vector2f uv = face.HeadLayoutUv(face.mesh.uvs[i]);
    const std::optional<Eigen::Vector3f> p = SampleGeometryMap(map, uv),
                                         pu = SampleGeometryMap(map, uv + Eigen::Vector2f(du, 0)),
                                         pv = SampleGeometryMap(map, uv + Eigen::Vector2f(0, du));
    if (!p || !pu || !pv) continue;
    const Eigen::Vector3f n = (*pu - *p).cross(*pv - *p).normalized();
    const Eigen::Vector3f e = fit.positions[i] - *p;
    const float along = n.dot(e), sliding = (e - along * n).norm();
    Errors& r = by_region[static_cast<int>(face.regions[i])];
    r.full.push_back(e.norm());
    r.sliding.push_back(sliding);
    r.sum2 += e.squaredNorm();
    r.normal2 += along * along;
    r.sliding2 += sliding * sliding;
  }
  auto summary = [](const Errors& r) {
    FitError f;
    f.vertices = static_cast<int64_t>(r.full.size());
    if (f.vertices == 0) return f;
    const double n = static_cast<double>(f.vertices);
    f.rmse_mm = std::sqrt(r.sum2 / n);
    f.p99_mm = Quantile(r.full, 99, 100);
    f.surface_rmse_mm = std::sqrt(r.normal2 / n);
    f.sliding_rmse_mm = std::sqrt(r.sliding2 / n);
    f.sliding_p99_mm = Quantile(r.sliding, 99, 100);
    return f;
  };
  FitEvaluation out;
  out.skin = summary(by_region[static_cast<int>(FaceRegion::kSkin)]);
  out.eyes = summary(by_region[static_cast<int>(FaceRegion::kEye)]);
  out.mouth = summary(by_region[static_cast<int>(FaceRegion::kMouth)]);
  return out;
}

namespace {

std::string PoseJson(const TemplateFit& fit, int64_t frame) {
  nlohmann::ordered_json j;
  j["frame"] = frame;
  std::vector<float> m(16);
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) m[static_cast<size_t>(4 * r + c)] = fit.stage_from_head.matrix()(r, c);
  }
  j["stage_from_head"] = m;  // row-major 4 x 4, mm
  j["scale"] = fit.scale;
  j["jaw_deg"] = fit.jaw_rad * 180 / kPi;
  if (!fit.identity.empty()) j["identity"] = fit.identity;        // the model's coefficients, standard deviations
  if (!fit.expression.empty()) j["expression"] = fit.expression;  // blendshape weights, the template's names
  return j.dump(2) + "\n";
}

// One frame's results in `dir`: the fitted mesh, its geometry map (head frame), the pose and the metrics.
absl::Status WriteFitFrame(const FaceTemplate& face, const TemplateFit& fit, const GeometryMapOptions& map_options,
                           const std::string& surface_file, const std::string& dir, int64_t frame) {
  TriangleMesh mesh = face.mesh;
  mesh.positions = fit.positions;
  STAGE_ASSIGN_OR_RETURN(const GeometryMap map, MakeGeometryMap(mesh, fit.stage_from_head.inverse(), map_options));
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  STAGE_RETURN_IF_ERROR(
      WriteObj(dir + "/mesh.obj", mesh, "FaStage face template fitted: stage frame, mm (docs/assets.md)"));
  STAGE_RETURN_IF_ERROR(WriteGeometryMap(dir + "/geometry_map.exr", map));
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(dir + "/pose.json", PoseJson(fit, frame)));
  nlohmann::ordered_json metrics;
  metrics["frame"] = frame;
  metrics["surface"] = surface_file;
  metrics["matched_vertices"] = fit.matched;
  metrics["template_vertices"] = face.mesh.positions.size();
  metrics["rms_to_surface_mm"] = fit.rms_mm;
  metrics["geometry_map_covered"] = map.Count(TexelState::kCovered);
  return WriteFileAtomically(dir + "/metrics.json", metrics.dump(2) + "\n");
}

// What ran, for whoever reads the results (no times or hosts: the same job writes the same bytes).
std::string RunJson(const FitJob& job, int64_t last) {
  nlohmann::ordered_json run;
  run["stage"] = "fit";
  run["take"] = std::filesystem::path(job.take_dir).filename().string();
  run["frames"] = {job.first_frame, last};
  run["surface"] = job.surface.ToString();
  run["template"] = job.template_obj.empty() ? "shipped (processing/data/face-template.obj)" : job.template_obj;
  run["geometry_map"] = {{"size", job.map.size}, {"dilation_px", job.map.dilation_px}};
  run["options"] = {{"rigid_iterations", job.options.rigid_iterations},
                    {"fit_scale", job.options.fit_scale},
                    {"stiffness", job.options.stiffness},
                    {"iterations_per_stage", job.options.iterations_per_stage},
                    {"max_distance_mm", job.options.max_distance_mm},
                    {"max_normal_angle_deg", job.options.max_normal_angle_deg},
                    {"skip_border", job.options.skip_border},
                    {"nonrigid", NonRigidMotionName(job.options.nonrigid)},
                    {"model_iterations", job.options.model_iterations},
                    {"identity_prior", job.options.identity_prior},
                    {"expression_prior", job.options.expression_prior},
                    {"identity_reach", job.options.identity_reach}};
  return run.dump(2) + "\n";
}

}  // namespace

absl::StatusOr<JobResult> RunFit(const FitJob& job, const std::function<void(const JobProgress&)>& progress,
                                 const std::function<bool()>& cancelled) {
  STAGE_RETURN_IF_ERROR(job.options.Validate());
  STAGE_RETURN_IF_ERROR(job.map.Validate());
  STAGE_RETURN_IF_ERROR(job.surface.Validate());
  if (!job.surface.has_mesh()) return absl::InvalidArgumentError("fit: the template is fitted to surfaces: not none");
  auto face = job.template_obj.empty() ? ShippedFaceTemplate() : LoadFaceTemplate(job.template_obj);
  if (!face.ok()) return face.status();
  const std::string rel = job.surface.RelativeDir(), surfaces = job.surface.Root(job.take_dir);
  if (!std::filesystem::is_directory(surfaces)) {
    return absl::NotFoundError(absl::StrCat(surfaces, ": no surfaces to fit (run the mvs stage first)"));
  }
  const int64_t last = job.last_frame >= 0 ? job.last_frame : EndOfFrames(surfaces, "mesh.obj", job.first_frame);
  if (job.first_frame < 0 || last <= job.first_frame) {
    return absl::InvalidArgumentError(absl::StrCat(surfaces, ": no frames [", job.first_frame, ", ", last, ")"));
  }
  JobResult result;
  result.output_dir = job.output_dir.empty() ? job.take_dir + "/derived/fit" : job.output_dir;
  JobProgress p{0, last - job.first_frame, absl::StrCat("template fit: ", last - job.first_frame, " frame(s)")};
  if (progress) progress(p);
  TemplateFit previous = StartAt(*face, Eigen::Isometry3f::Identity());
  for (int64_t frame = job.first_frame; frame < last; ++frame) {
    if (cancelled && cancelled()) {
      return absl::CancelledError(
          absl::StrCat("template fit on ", job.take_dir, " cancelled after ", result.units, " frame(s)"));
    }
    auto surface = ReadObj(FrameDir(surfaces, frame) + "/mesh.obj");
    if (!surface.ok()) return surface.status();
    auto fit = FitTemplate(*face, *surface, previous, job.options);
    if (!fit.ok()) {
      return absl::Status(fit.status().code(),
                          absl::StrCat(job.take_dir, ": frame ", frame, ": ", fit.status().message()));
    }
    STAGE_RETURN_IF_ERROR(WriteFitFrame(*face, *fit, job.map, FrameDir(rel, frame) + "/mesh.obj",
                                        FrameDir(result.output_dir, frame), frame));
    previous = *std::move(fit);
    ++result.units;
    p.done = result.units;
    p.message = absl::StrFormat("frame %d: %d of %d vertices on the surface, %.3f mm rms", frame, previous.matched,
                                face->mesh.positions.size(), previous.rms_mm);
    if (progress) progress(p);
  }
  STAGE_RETURN_IF_ERROR(WriteFileAtomically(result.output_dir + "/run.json", RunJson(job, last)));
  return result;
}

}  // namespace stage::processing
