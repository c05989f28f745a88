#include "stage/processing/uv_geometry.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "absl/strings/str_cat.h"
#include "gap_fill.h"
#include "stage/common/status.h"
#include "stage/common/uv_raster.h"
#include "stage/processing/map_files.h"
#include "statistics.h"

namespace stage::processing {

absl::Status GeometryMapOptions::Validate() const {
  if (size < 16 || size > 8192) {
    return absl::InvalidArgumentError(absl::StrCat("geometry map: size ", size, " is not in 16..8192"));
  }
  if (dilation_px < 0 || dilation_px > 64) {
    return absl::InvalidArgumentError(absl::StrCat("geometry map: dilation_px ", dilation_px, " is not in 0..64"));
  }
  if (part < -1 || part > 255) {
    return absl::InvalidArgumentError(absl::StrCat("geometry map: part ", part, " is not -1 (every part) or 0..255"));
  }
  return absl::OkStatus();
}

int64_t GeometryMap::Count(TexelState s) const { return std::count(state.begin(), state.end(), s); }

absl::StatusOr<GeometryMap> MakeGeometryMap(const TriangleMesh& mesh, const Eigen::Isometry3f& head_from_stage,
                                            const GeometryMapOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  if (mesh.uvs.size() != mesh.positions.size() || mesh.positions.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("geometry map: the mesh has ", mesh.uvs.size(),
                                                   " texture coordinates for ", mesh.positions.size(), " vertices"));
  }
  std::vector<Eigen::Vector3f> head(mesh.positions.size());
  for (size_t v = 0; v < head.size(); ++v) head[v] = head_from_stage * mesh.positions[v];
  const std::vector<UvTexel> texels = RasterizeUv(mesh, options.size, options.part);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  GeometryMap map;
  map.size = options.size;
  map.points = InterpolateAtTexels(mesh, texels, head, Eigen::Vector3f::Constant(nan));
  map.state.resize(texels.size());
  std::vector<float> flat(3 * texels.size());
  for (size_t i = 0; i < texels.size(); ++i) {
    map.state[i] = texels[i].covered() ? TexelState::kCovered : TexelState::kEmpty;
    std::copy(map.points[i].data(), map.points[i].data() + 3, &flat[3 * i]);
  }
  GrowIntoGaps(options.size, options.size, /*channels=*/3, options.dilation_px, GapGrowth::kLinear, &flat);
  for (size_t i = 0; i < texels.size(); ++i) {
    if (map.state[i] != TexelState::kEmpty || flat[3 * i] != flat[3 * i]) continue;
    map.points[i] = Eigen::Map<const Eigen::Vector3f>(&flat[3 * i]);
    map.state[i] = TexelState::kDilated;
  }
  return map;
}

std::optional<Eigen::Vector3f> SampleGeometryMap(const GeometryMap& map, const Eigen::Vector2f& uv) {
  const int n = map.size;
  // Texel centres sit at integer + 0.5 (x right, rows down from v = 1).
  const float fx = std::clamp(uv.x(), 0.0f, 1.0f) * static_cast<float>(n) - 0.5f,
              fy = (1.0f - std::clamp(uv.y(), 0.0f, 1.0f)) * static_cast<float>(n) - 0.5f;
  const int x0 = static_cast<int>(std::floor(fx)), y0 = static_cast<int>(std::floor(fy));
  const float ax = fx - static_cast<float>(x0), ay = fy - static_cast<float>(y0);
  // Within half a texel of the map's border (x or y at -1 or n) the two texels inside are extrapolated linearly: a
  // clamp would put the border's points half a texel inwards.
  auto texel = [&](int x, int y) -> std::optional<Eigen::Vector3f> {
    const size_t i = static_cast<size_t>(y) * n + x;
    if (map.state[i] == TexelState::kEmpty) return std::nullopt;
    return map.points[i];
  };
  auto at = [&](int x, int y) -> std::optional<Eigen::Vector3f> {
    const int cx = std::clamp(x, 0, n - 1), cy = std::clamp(y, 0, n - 1);
    auto inside = texel(cx, cy);
    if (!inside || (cx == x && cy == y)) return inside;
    const int ix = x < 0 ? 1 : x >= n ? n - 2 : cx, iy = y < 0 ? 1 : y >= n ? n - 2 : cy;
    auto next = texel(ix, iy);
    if (!next) return inside;
    return Eigen::Vector3f(2 * *inside - *next);
  };
  Eigen::Vector3f sum = Eigen::Vector3f::Zero();
  for (int dy = 0; dy < 2; ++dy) {
    for (int dx = 0; dx < 2; ++dx) {
      const std::optional<Eigen::Vector3f> p = at(x0 + dx, y0 + dy);
      if (!p) return std::nullopt;
      sum += (dx ? ax : 1 - ax) * (dy ? ay : 1 - ay) * *p;
    }
  }
  return sum;
}

RoundTripError MeasureRoundTrip(const TriangleMesh& mesh, const Eigen::Isometry3f& head_from_stage,
                                const GeometryMap& map, int part) {
  RoundTripError e;
  std::vector<float> errors;
  auto sample = [&](const Eigen::Vector2f& uv, const Eigen::Vector3f& stage_point) {
    ++e.samples;
    const std::optional<Eigen::Vector3f> p = SampleGeometryMap(map, uv);
    if (!p) {
      ++e.missed;
      return;
    }
    errors.push_back((*p - head_from_stage * stage_point).norm());
  };
  std::vector<uint8_t> used(mesh.positions.size(), 0);
  for (size_t k = 0; k < mesh.triangles.size(); ++k) {
    if (part >= 0 && (mesh.parts.empty() ? 0 : mesh.parts[k]) != part) continue;
    const auto& t = mesh.triangles[k];
    for (int32_t v : t) used[static_cast<size_t>(v)] = 1;
    sample((mesh.uvs[t[0]] + mesh.uvs[t[1]] + mesh.uvs[t[2]]) / 3,
           (mesh.positions[t[0]] + mesh.positions[t[1]] + mesh.positions[t[2]]) / 3);
  }
  for (size_t v = 0; v < used.size(); ++v) {
    if (used[v]) sample(mesh.uvs[v], mesh.positions[v]);
  }
  if (errors.empty()) return e;
  double sum = 0;
  for (float d : errors) sum += d;
  e.mean_mm = sum / static_cast<double>(errors.size());
  e.p99_mm = Quantile(errors, 99, 100);
  e.max_mm = *std::max_element(errors.begin(), errors.end());
  return e;
}

absl::Status WriteGeometryMap(const std::string& path, const GeometryMap& map) {
  Image image(map.size, map.size, 4);
  for (size_t i = 0; i < map.state.size(); ++i) {
    float* o = &image.pixels[4 * i];
    if (map.state[i] == TexelState::kEmpty) continue;
    std::copy(map.points[i].data(), map.points[i].data() + 3, o);
    o[3] = map.state[i] == TexelState::kCovered ? 1.0f : 0.5f;
  }
  return WriteExr(path, image);
}

absl::StatusOr<GeometryMap> ReadGeometryMap(const std::string& path) {
  auto image = ReadImageFile(path);
  if (!image.ok()) return image.status();
  if (image->channels != 4 || image->width != image->height) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": a geometry map is square RGBA; this is ", image->width,
                                                   " x ", image->height, " with ", image->channels, " channel(s)"));
  }
  GeometryMap map;
  map.size = image->width;
  map.points.assign(image->pixels.size() / 4, Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN()));
  map.state.assign(map.points.size(), TexelState::kEmpty);
  for (size_t i = 0; i < map.points.size(); ++i) {
    const float* p = &image->pixels[4 * i];
    if (p[3] == 0) continue;
    if (p[3] != 1 && p[3] != 0.5f) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": texel ", i % map.size, ", ", i / map.size, " has alpha ",
                                                     p[3], " (1 covered, 0.5 dilated, 0 empty)"));
    }
    map.points[i] = Eigen::Map<const Eigen::Vector3f>(p);
    map.state[i] = p[3] == 1 ? TexelState::kCovered : TexelState::kDilated;
  }
  return map;
}

}  // namespace stage::processing
