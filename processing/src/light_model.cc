// The stage's light for photometric stereo: see light_model.h.
#include "stage/processing/light_model.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/timing/pattern_set.h"

namespace stage::processing {

absl::StatusOr<LightModel> LightModel::FromRig(const LoadedRig& rig) {
  auto set = timing::LoadRigPatternSet(rig.rig, rig.base_dir);
  if (!set.ok()) return set.status();
  LightModel m;
  if (rig.rig.sim().has_dome_radius_mm()) m.radius_mm = rig.rig.sim().dome_radius_mm();
  for (const auto& node : rig.rig.light_nodes()) {
    for (const auto& u : node.units()) {
      Eigen::Vector3d d(u.direction().x(), u.direction().y(), u.direction().z());
      if (d.norm() < 1e-9) return absl::InvalidArgumentError(absl::StrCat("LED unit \"", u.id(), "\": no direction"));
      m.directions.push_back(d.normalized());
      m.intensity.push_back(u.has_intensity_scale() ? u.intensity_scale() : 1.0);
    }
  }
  if (m.directions.size() != set->unit_ids.size()) {
    return absl::InternalError(
        absl::StrCat("the pattern set has ", set->unit_ids.size(), " units, the rig ", m.directions.size()));
  }
  for (const timing::Pattern& p : set->patterns) {
    LightPattern lp;
    lp.name = p.name;
    lp.parallel = p.polarization == v1::POLARIZATION_PARALLEL;
    for (double w : p.weights) lp.weights.push_back(std::round(w * 65535.0) / 65535.0);  // as the nodes drive it
    m.patterns.push_back(std::move(lp));
  }
  return m;
}

absl::StatusOr<int> LightModel::Find(absl::string_view name) const {
  std::vector<std::string> names;
  for (size_t i = 0; i < patterns.size(); ++i) {
    if (patterns[i].name == name) return static_cast<int>(i);
    names.push_back(patterns[i].name);
  }
  return absl::NotFoundError(
      absl::StrCat("the pattern set has no pattern \"", name, "\" (it has ", absl::StrJoin(names, ", "), ")"));
}

Eigen::Vector3d LightModel::DiffuseVector(int pattern, const Eigen::Vector3d& n) const {
  Eigen::Vector3d h = Eigen::Vector3d::Zero();
  const std::vector<double>& w = patterns[static_cast<size_t>(pattern)].weights;
  for (size_t l = 0; l < directions.size(); ++l) {
    if (n.dot(directions[l]) > 0) h += w[l] * intensity[l] * directions[l];
  }
  return h;
}

void LightModel::ViewFrom(const Eigen::Vector3d& x, const uint64_t* visible, UnitView* view) const {
  const size_t n = directions.size();
  view->direction.resize(n);
  view->gain.resize(n);
  const double r2 = radius_mm * radius_mm;
  for (size_t l = 0; l < n; ++l) {
    const Eigen::Vector3d to = directions[l] * radius_mm - x;
    const double d2 = to.squaredNorm();
    view->direction[l] = (to / std::sqrt(d2)).cast<float>();
    const bool seen = visible == nullptr || ((visible[l / 64] >> (l % 64)) & 1u) != 0;
    view->gain[l] = seen ? static_cast<float>(intensity[l] * r2 / d2) : 0.f;
  }
}

UnitView LightModel::ViewFromOrigin() const {
  UnitView view;
  for (size_t l = 0; l < directions.size(); ++l) {
    view.direction.push_back(directions[l].cast<float>());
    view.gain.push_back(static_cast<float>(intensity[l]));
  }
  return view;
}

Eigen::Vector2f OctEncode(const Eigen::Vector3f& n) {
  const float s = std::abs(n.x()) + std::abs(n.y()) + std::abs(n.z());
  float x = n.x() / s, y = n.y() / s;
  if (n.z() < 0) {
    const float ox = (1 - std::abs(y)) * (x >= 0 ? 1.f : -1.f);
    const float oy = (1 - std::abs(x)) * (y >= 0 ? 1.f : -1.f);
    x = ox;
    y = oy;
  }
  return {x * 0.5f + 0.5f, y * 0.5f + 0.5f};
}

Eigen::Vector3f OctDecode(const Eigen::Vector2f& uv) {
  const float x = uv.x() * 2 - 1, y = uv.y() * 2 - 1;
  Eigen::Vector3f n(x, y, 1 - std::abs(x) - std::abs(y));
  if (n.z() < 0) {
    const float ox = (1 - std::abs(y)) * (x >= 0 ? 1.f : -1.f);
    const float oy = (1 - std::abs(x)) * (y >= 0 ? 1.f : -1.f);
    n.x() = ox;
    n.y() = oy;
  }
  return n.normalized();
}

DiffuseTable::DiffuseTable(const LightModel& model, const std::vector<int>& patterns, int size)
    : patterns_(patterns), size_(size), table_(static_cast<size_t>(size) * size * patterns.size() * 3) {
  const size_t np = patterns_.size();
  for (int v = 0; v < size_; ++v) {
    for (int u = 0; u < size_; ++u) {
      // Cell centres; the map's edges are where the lower hemisphere folds, so sample at (i + 0.5) / size.
      const Eigen::Vector3f n = OctDecode({(u + 0.5f) / size_, (v + 0.5f) / size_});
      float* cell = &table_[(static_cast<size_t>(v) * size_ + u) * np * 3];
      for (size_t p = 0; p < np; ++p) {
        const Eigen::Vector3d h = model.DiffuseVector(patterns_[p], n.cast<double>());
        cell[3 * p] = static_cast<float>(h.x());
        cell[3 * p + 1] = static_cast<float>(h.y());
        cell[3 * p + 2] = static_cast<float>(h.z());
      }
    }
  }
}

void DiffuseTable::Lookup(const Eigen::Vector3f& n, float* out) const {
  const Eigen::Vector2f uv = OctEncode(n);
  const float fu = std::clamp(uv.x() * size_ - 0.5f, 0.f, size_ - 1.001f);
  const float fv = std::clamp(uv.y() * size_ - 0.5f, 0.f, size_ - 1.001f);
  const int u0 = static_cast<int>(fu), v0 = static_cast<int>(fv);
  const float a = fu - u0, b = fv - v0;
  const size_t np3 = patterns_.size() * 3;
  const float* c00 = &table_[(static_cast<size_t>(v0) * size_ + u0) * np3];
  const float* c01 = c00 + np3;
  const float* c10 = c00 + static_cast<size_t>(size_) * np3;
  const float* c11 = c10 + np3;
  const float w00 = (1 - a) * (1 - b), w01 = a * (1 - b), w10 = (1 - a) * b, w11 = a * b;
  for (size_t i = 0; i < np3; ++i) out[i] = w00 * c00[i] + w01 * c01[i] + w10 * c10[i] + w11 * c11[i];
}

}  // namespace stage::processing
