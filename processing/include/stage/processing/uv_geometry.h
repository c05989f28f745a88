// UV geometry maps (docs/assets.md): a mesh's surface drawn into its UV layout, per texel the 3D point there in the
// head's frame (millimetres; the head's pose taken out and kept apart), dilated past the layout's edges and seams so
// that filtering near them reads geometry, not zeros. And back: the map sampled at a layout's texture coordinates
// gives the mesh of that topology. The texel convention is stage/common/uv_raster.h's (row 0 at v = 1).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/common/mesh.h"

namespace stage::processing {

struct GeometryMapOptions {
  // Texels across the square map (16..8192).
  int size = 256;
  // Rings of texels grown past the covered ones, each continuing its set neighbours linearly (0..64).
  int dilation_px = 4;
  // The mesh's part drawn (stage/common/mesh.h: 0 skin, 1 eyes); -1: every part.
  int part = 0;

  absl::Status Validate() const;
};

enum class TexelState : uint8_t {
  kEmpty = 0,    // no triangle covers it, nor is it within the dilation of one that does
  kCovered = 1,  // the surface's point at the texel's centre
  kDilated = 2,  // grown from covered neighbours (past an edge or seam of the layout)
};

struct GeometryMap {
  int size = 0;
  // Per texel (row-major), head frame, mm; NaN where empty.
  std::vector<Eigen::Vector3f> points;
  std::vector<TexelState> state;

  int64_t Count(TexelState s) const;
};

// Draws `mesh` (stage frame, mm, with a uv per vertex) into its UV layout; every point is taken to the head's frame by
// `head_from_stage` (identity: the stage frame). Errors: options out of range, a mesh without texture coordinates.
absl::StatusOr<GeometryMap> MakeGeometryMap(const TriangleMesh& mesh, const Eigen::Isometry3f& head_from_stage,
                                            const GeometryMapOptions& options);

// The map at texture coordinates `uv`, interpolated bilinearly between the four nearest texel centres (clamped at the
// map's border); nullopt where one of them is empty.
std::optional<Eigen::Vector3f> SampleGeometryMap(const GeometryMap& map, const Eigen::Vector2f& uv);

// mesh -> map -> mesh: how far from where it is every vertex and triangle centre of `mesh` (of the map's part) comes
// back when sampled from `map` (made from `mesh` with the same `head_from_stage`).
struct RoundTripError {
  int64_t samples = 0;  // points sampled
  int64_t missed = 0;   // points where the map had an empty texel
  double mean_mm = 0, p99_mm = 0, max_mm = 0;
};
RoundTripError MeasureRoundTrip(const TriangleMesh& mesh, const Eigen::Isometry3f& head_from_stage,
                                const GeometryMap& map, int part = 0);

// OpenEXR, float32 RGBA: x, y, z in mm and alpha 1 (covered), 0.5 (dilated) or 0 (empty, with x = y = z = 0).
absl::Status WriteGeometryMap(const std::string& path, const GeometryMap& map);
// Reads WriteGeometryMap's file back. Errors name the file: not square, not 4 channels, an alpha of another value.
absl::StatusOr<GeometryMap> ReadGeometryMap(const std::string& path);

}  // namespace stage::processing
