// What the simulated cameras look at. A subject answers rays: where a ray first meets it, with the surface's normal
// and material there, and whether a segment is blocked (self-shadowing). Kinds: analytic sphere and plane (for
// checks against closed forms); the procedural head and the calibration board build on the same interface.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <span>

namespace stage::sim {

// Surface reflectance at a point: Lambertian diffuse plus a GGX microfacet specular lobe.
struct Material {
  // Diffuse albedo, linear RGB in [0, 1].
  Eigen::Vector3f albedo = Eigen::Vector3f::Constant(0.5f);
  // Specular intensity: the lobe's reflectance at normal incidence (Fresnel folded in), e.g. 0.03 for skin.
  float specular = 0.03f;
  // GGX roughness alpha (the lobe's width; alpha = 0.3 is typical of skin).
  float roughness = 0.3f;
};

struct Hit {
  bool hit = false;
  // Distance along the (unit) ray, mm.
  float t = 0;
  Eigen::Vector3f point = Eigen::Vector3f::Zero();
  // Geometric normal (of the surface itself) and shading normal (with detail), unit, facing the ray's origin.
  Eigen::Vector3f geometric_normal = Eigen::Vector3f::UnitZ();
  Eigen::Vector3f normal = Eigen::Vector3f::UnitZ();
  Material material;
  // Texture coordinates of the point (meshes; 0 elsewhere) and which part it belongs to (0 skin, 1 eye).
  Eigen::Vector2f uv = Eigen::Vector2f::Zero();
  int part = 0;
};

class Subject {
 public:
  virtual ~Subject() = default;
  // The first intersection of the ray origin + t * direction (direction unit), t > 0.
  virtual Hit Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const = 0;
  // True if the segment from `from` towards `to` is blocked by the subject before reaching `to`. `from` is a surface
  // point: the caller offsets it along the normal.
  virtual bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const = 0;
  // Occluded for many segments at once (`blocked[i]` for from[i] -> to[i], spans of one size). The renderer hands in
  // neighbouring points' segments towards one light after another; a mesh traces them together (MeshSubject: Embree's
  // packets), any other subject one at a time (this default).
  virtual void OccludedMany(std::span<const Eigen::Vector3f> from, std::span<const Eigen::Vector3f> to,
                            std::span<uint8_t> blocked) const;
  // The albedo where the ray first meets the subject, false where it misses: Intersect's material.albedo, which a
  // subject may find without the rest of the hit (a mesh: no normals, no bump). What a pixel's texture samples need.
  virtual bool AlbedoAt(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction, Eigen::Vector3f* albedo) const;
  // True if no point of the subject's surface can shadow another: a surface point sees every point in front of its
  // tangent plane, so the renderer skips shadow rays towards those (a sphere, a plate; never a head).
  virtual bool Convex() const { return false; }
};

class SphereSubject final : public Subject {
 public:
  SphereSubject(Eigen::Vector3f center, float radius, Material material)
      : center_(std::move(center)), radius_(radius), material_(material) {}
  Hit Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const override;
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const override;
  bool Convex() const override { return true; }

 private:
  Eigen::Vector3f center_;
  float radius_;
  Material material_;
};

// A square of side `size` centred at `center`, facing `normal`, one-sided.
class PlaneSubject final : public Subject {
 public:
  PlaneSubject(Eigen::Vector3f center, Eigen::Vector3f normal, float size, Material material);
  Hit Intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction) const override;
  bool Occluded(const Eigen::Vector3f& from, const Eigen::Vector3f& to) const override;
  bool Convex() const override { return true; }

 private:
  Eigen::Vector3f center_, normal_, u_, v_;
  float half_;
  Material material_;
};

}  // namespace stage::sim
