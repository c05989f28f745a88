// Analytic subjects.
#include "stage/sim/subject.h"

#include <Eigen/Geometry>
#include <cmath>

namespace stage::sim {

bool Subject::AlbedoAt(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, Eigen::Vector3f* albedo) const {
  const Hit h = Intersect(origin, direction);
  if (h.hit) *albedo = h.material.albedo;
  return h.hit;
}

void Subject::OccludedMany(std::span<const Eigen::Vector3f> from, std::span<const Eigen::Vector3f> to,
                           std::span<uint8_t> blocked) const {
  for (size_t i = 0; i < from.size(); ++i) blocked[i] = Occluded(from[i], to[i]) ? 1 : 0;
}

Hit SphereSubject::Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const {
  // |o + t d - c|^2 = r^2 with |d| = 1: t^2 + 2 b t + c = 0, in double precision: near the silhouette the root is
  // ill-conditioned and float would move the hit point by millimetres.
  const Eigen::Vector3d d = direction.cast<double>().normalized();
  const Eigen::Vector3d oc = origin.cast<double>() - center_.cast<double>();
  const double b = oc.dot(d);
  const double c = oc.squaredNorm() - static_cast<double>(radius_) * radius_;
  const double disc = b * b - c;
  Hit hit;
  if (disc < 0) return hit;
  const double s = std::sqrt(disc);
  double t = -b - s;
  if (t <= 1e-4) t = -b + s;
  if (t <= 1e-4) return hit;
  hit.hit = true;
  hit.t = static_cast<float>(t);
  const Eigen::Vector3d p = origin.cast<double>() + t * d;
  hit.point = p.cast<float>();
  hit.geometric_normal = ((p - center_.cast<double>()) / radius_).normalized().cast<float>();
  hit.normal = hit.geometric_normal;
  hit.material = material_;
  return hit;
}

bool SphereSubject::Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const {
  const Eigen::Vector3f d = to - from;
  const float len = d.norm();
  Hit h = Intersect(from, d / len);
  return h.hit && h.t < len;
}

PlaneSubject::PlaneSubject(Eigen::Vector3f center, Eigen::Vector3f normal, float size, Material material)
    : center_(std::move(center)), normal_(normal.normalized()), half_(size / 2), material_(material) {
  const Eigen::Vector3f helper = std::abs(normal_.y()) < 0.9f ? Eigen::Vector3f::UnitY() : Eigen::Vector3f::UnitX();
  u_ = helper.cross(normal_).normalized();
  v_ = normal_.cross(u_);
}

Hit PlaneSubject::Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const {
  Hit hit;
  const float denom = direction.dot(normal_);
  if (denom >= -1e-9f) return hit;  // one-sided: seen from the front only
  const float t = (center_ - origin).dot(normal_) / denom;
  if (t <= 1e-4f) return hit;
  const Eigen::Vector3f p = origin + t * direction;
  const Eigen::Vector3f q = p - center_;
  if (std::abs(q.dot(u_)) > half_ || std::abs(q.dot(v_)) > half_) return hit;
  hit.hit = true;
  hit.t = t;
  hit.point = p;
  hit.geometric_normal = normal_;
  hit.normal = normal_;
  hit.material = material_;
  return hit;
}

bool PlaneSubject::Occluded(const Eigen::Vector3f&, const Eigen::Vector3f&) const {
  return false;  // a flat one-sided square cannot shadow itself
}

}  // namespace stage::sim
