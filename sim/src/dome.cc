// The simulated dome.
#include "stage/sim/dome.h"

#include <cmath>

namespace stage::sim {

Dome Dome::FromRig(const v1::RigConfig& rig, double radius_mm) {
  Dome dome;
  for (int n = 0; n < rig.light_nodes_size(); ++n) {
    for (const v1::LedUnit& u : rig.light_nodes(n).units()) {
      LedUnitModel m;
      m.id = u.id();
      Eigen::Vector3d d(u.direction().x(), u.direction().y(), u.direction().z());
      m.direction = d.norm() > 0 ? d.normalized() : Eigen::Vector3d::UnitZ();
      m.position = m.direction * radius_mm;
      m.intensity = u.has_intensity_scale() ? u.intensity_scale() : 1.0;
      m.node = n;
      m.parallel_channel = u.parallel_channel();
      m.cross_channel = u.cross_channel();
      dome.units.push_back(std::move(m));
    }
  }
  return dome;
}

Dome Dome::FromDirections(const std::vector<Eigen::Vector3d>& directions, double radius_mm, double intensity) {
  Dome dome;
  for (size_t i = 0; i < directions.size(); ++i) {
    LedUnitModel m;
    m.id = "u" + std::to_string(i);
    m.direction = directions[i].normalized();
    m.position = m.direction * radius_mm;
    m.intensity = intensity;
    m.parallel_channel = static_cast<uint32_t>(2 * i);
    m.cross_channel = static_cast<uint32_t>(2 * i + 1);
    dome.units.push_back(std::move(m));
  }
  return dome;
}

std::vector<Eigen::Vector3d> FibonacciSphere(int n) {
  std::vector<Eigen::Vector3d> out;
  const double golden = M_PI * (3 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double y = 1 - 2 * (i + 0.5) / n;
    const double r = std::sqrt(1 - y * y);
    const double theta = golden * i;
    out.emplace_back(r * std::cos(theta), y, r * std::sin(theta));
  }
  return out;
}

}  // namespace stage::sim
