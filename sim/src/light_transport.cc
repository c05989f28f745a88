// Per-pixel LED responses and exposures.
#include "stage/sim/light_transport.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <span>
#include <thread>

#include "absl/strings/str_format.h"

namespace stage::sim {
namespace {

constexpr float kPi = 3.14159265358979323846f;
// Shadow rays start this far off the surface, mm.
constexpr float kShadowEpsilon = 1e-3f;

// Runs body(0..n-1) on `threads` threads; each thread adds what it has done to `progress` every 64 items, each item
// `work` units of it. Fewer than `min_parallel` items run on the calling thread.
template <typename F>
void ParallelFor(size_t n, int threads, WorkProgress* progress, F&& body, uint64_t work = 1, size_t min_parallel = 64) {
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  auto run = [&](size_t first, size_t step) {
    uint64_t since = 0;
    for (size_t i = first; i < n; i += step) {
      body(i);
      if (progress != nullptr && ++since == 64) {
        progress->done.fetch_add(since * work, std::memory_order_relaxed);
        since = 0;
      }
    }
    if (progress != nullptr) progress->done.fetch_add(since * work, std::memory_order_relaxed);
  };
  if (threads == 1 || n < min_parallel) {
    run(0, 1);
    return;
  }
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t)
    pool.emplace_back([&, t] { run(static_cast<size_t>(t), static_cast<size_t>(threads)); });
  for (auto& th : pool) th.join();
}

// The dome's units as arrays of floats: the loop over units below reads them with unit stride.
struct UnitArrays {
  explicit UnitArrays(const Dome& dome) {
    for (const auto& u : dome.units) {
      x.push_back(static_cast<float>(u.position.x()));
      y.push_back(static_cast<float>(u.position.y()));
      z.push_back(static_cast<float>(u.position.z()));
      intensity.push_back(static_cast<float>(u.intensity));
    }
  }
  std::vector<float> x, y, z, intensity;
};

// What the loop over units needs of one ray's hit.
struct HitTerms {
  float px, py, pz;  // the point
  float nx, ny, nz;  // the shading normal
  float gx, gy, gz;  // the geometric normal
  float vx, vy, vz;  // towards the camera
  float alpha;       // the roughness (at least 1e-3)
  float view;        // the specular lobe's terms of the view alone (0: the view is behind the shading normal)
  Eigen::Vector3f start;
};

// Whether a hit faces unit l: in front of its shading and its geometric normal (no short cut: no branch).
inline bool Faces(const HitTerms& t, float wx, float wy, float wz) {
  return (t.nx * wx + t.ny * wy + t.nz * wz > 0) & (t.gx * wx + t.gy * wy + t.gz * wz > 0);
}

// The hit's diffuse and specular response to every unit, added to `d` and `s`. With shadows (kShadows), `dark` says
// per unit whether it lights the hit (0) or not (1: behind it or shadowed; DarkUnits), the one place that decides;
// without, the hit's facing does. The loop has no branch and GCC vectorizes it (-O3, no errno or traps: sqrt, and the
// divisions of units behind the surface, are computed and not selected).
template <bool kShadows>
void AddUnitResponses(const HitTerms& terms, const UnitArrays& units, const uint8_t* dark, float weight, float* d,
                      float* s) {
  // Copies and plain pointers: the rows written cannot alias them.
  const HitTerms t = terms;
  const float *ux = units.x.data(), *uy = units.y.data(), *uz = units.z.data(), *ui = units.intensity.data();
  const size_t count = units.x.size();
  for (size_t l = 0; l < count; ++l) {
    const float tx = ux[l] - t.px, ty = uy[l] - t.py, tz = uz[l] - t.pz;
    const float d2 = tx * tx + ty * ty + tz * tz;
    const float inv = 1.0f / std::sqrt(d2);
    const float wx = tx * inv, wy = ty * inv, wz = tz * inv;
    const float n_dot_w = t.nx * wx + t.ny * wy + t.nz * wz;
    bool lit;
    if constexpr (kShadows) {
      lit = dark[l] == 0;
    } else {
      lit = Faces(t, wx, wy, wz);
    }
    const float irradiance = weight * ui[l] / d2;
    const float hx = wx + t.vx, hy = wy + t.vy, hz = wz + t.vz;
    const float n_dot_h = (t.nx * hx + t.ny * hy + t.nz * hz) / std::sqrt(hx * hx + hy * hy + hz * hz);
    // Both computed for every unit, then selected: GCC vectorizes a select, not a condition around arithmetic.
    const float diffuse = n_dot_w * irradiance / kPi;
    const float specular = GgxDistribution(n_dot_h, t.alpha) * SmithG1(n_dot_w, t.alpha) * t.view * irradiance;
    d[l] += lit ? diffuse : 0.0f;
    s[l] += lit ? specular : 0.0f;
  }
}

// What the loop over units needs of one ray's hit, seen from the camera at `origin`.
HitTerms MakeTerms(const Hit& h, const Eigen::Vector3f& origin) {
  const Eigen::Vector3f v = (origin - h.point).normalized();
  const float n_dot_v = h.normal.dot(v);
  const float alpha = std::max(h.material.roughness, 1e-3f);
  return HitTerms{h.point.x(),
                  h.point.y(),
                  h.point.z(),
                  h.normal.x(),
                  h.normal.y(),
                  h.normal.z(),
                  h.geometric_normal.x(),
                  h.geometric_normal.y(),
                  h.geometric_normal.z(),
                  v.x(),
                  v.y(),
                  v.z(),
                  alpha,
                  n_dot_v > 0 ? h.material.specular * SmithG1(n_dot_v, alpha) / (4 * n_dot_v) : 0.0f,
                  h.point + kShadowEpsilon * h.geometric_normal};
}

// Hits whose responses are computed together (a block of neighbouring pixels, fewer where a pixel has several rays):
// their shadow rays towards one unit are traced as one stream.
constexpr size_t kBlockHits = 16;

// A thread's scratch for a block, reused from block to block.
struct BlockScratch {
  std::vector<HitTerms> terms;
  std::vector<Eigen::Index> rows;         // per hit: its row
  std::vector<uint8_t> dark;              // hits x units
  std::vector<Eigen::Vector3f> from, to;  // the shadow rays traced
  std::vector<uint32_t> ray_of;           // each one's index into `dark`
  std::vector<uint8_t> answers;
};

// For every hit of the block and every unit, whether the unit leaves it dark (`dark`, hits x units): behind it, or
// shadowed by the occluder. The rays go unit by unit, the block's neighbouring hits together: for one light they run
// side by side, the coherent stream Embree traces in packets.
void DarkUnits(const UnitArrays& units, const Subject& occluder, BlockScratch& b) {
  const size_t hits = b.terms.size(), count = units.x.size();
  b.dark.assign(hits * count, 1);
  b.from.clear();
  b.to.clear();
  b.ray_of.clear();
  for (size_t l = 0; l < count; ++l) {
    const Eigen::Vector3f unit(units.x[l], units.y[l], units.z[l]);
    for (size_t k = 0; k < hits; ++k) {
      const HitTerms& t = b.terms[k];
      const float tx = unit.x() - t.px, ty = unit.y() - t.py, tz = unit.z() - t.pz;
      const float inv = 1.0f / std::sqrt(tx * tx + ty * ty + tz * tz);
      if (!Faces(t, tx * inv, ty * inv, tz * inv)) continue;
      b.from.push_back(t.start);
      b.to.push_back(unit);
      b.ray_of.push_back(static_cast<uint32_t>(k * count + l));
    }
  }
  b.answers.resize(b.from.size());
  occluder.OccludedMany(b.from, b.to, b.answers);
  for (size_t i = 0; i < b.answers.size(); ++i) b.dark[b.ray_of[i]] = b.answers[i];
}

// A basis's drives, units x exposures: the diffuse (cross + parallel) and the specular (parallel + leakage cross) drive
// of each exposure.
struct BasisDrives {
  BasisDrives(const ExposureBasis& basis, size_t units)
      : diffuse(static_cast<Eigen::Index>(units), static_cast<Eigen::Index>(basis.levels.size())),
        specular(diffuse.rows(), diffuse.cols()) {
    for (Eigen::Index k = 0; k < diffuse.cols(); ++k) {
      const EmitterLevels& l = basis.levels[static_cast<size_t>(k)];
      if (l.cross.size() != diffuse.rows() || l.parallel.size() != diffuse.rows()) {
        // The renderer's own callers make the levels from the same dome; anything else is a programming error.
        std::fprintf(stderr, "ComputeResponses: exposure %ld of the basis has %ld/%ld levels for %ld units\n",
                     static_cast<long>(k), static_cast<long>(l.cross.size()), static_cast<long>(l.parallel.size()),
                     static_cast<long>(diffuse.rows()));
        std::abort();
      }
      diffuse.col(k) = l.cross + l.parallel;
      specular.col(k) = l.parallel + basis.leakage * l.cross;
    }
  }
  Eigen::MatrixXf diffuse, specular;
};

// The responses of rows [first, last) (their hits weighted by `weight`, a ray's share of the pixel) into `r`: to
// every unit, or where `drives` is given, summed under its exposures (the block's rows of every unit's responses made
// in a scratch matrix, then one product with the drives). `occluder`: the subject where it may shadow itself, null
// where it cannot (a convex subject shadows none of itself where the light is in front of the surface).
void AddBlockResponses(const std::vector<std::span<const Hit>>& rows, size_t first, size_t last,
                       const Eigen::Vector3f& origin, const UnitArrays& units, const Subject* occluder, float weight,
                       const BasisDrives* drives, PixelResponses& r) {
  thread_local BlockScratch b;
  thread_local RowMatrixXf unit_d, unit_s;  // the block's rows of every unit's responses, where projected
  const size_t count = units.x.size();
  const auto block_rows = static_cast<Eigen::Index>(last - first);
  if (drives != nullptr) {
    unit_d.setZero(block_rows, static_cast<Eigen::Index>(count));
    unit_s.setZero(block_rows, static_cast<Eigen::Index>(count));
  }
  b.terms.clear();
  b.rows.clear();
  for (size_t i = first; i < last; ++i) {
    const auto row = static_cast<Eigen::Index>(i);
    if (drives == nullptr) {
      r.diffuse.row(row).setZero();
      r.specular.row(row).setZero();
    }
    for (const Hit& h : rows[i]) {
      b.terms.push_back(MakeTerms(h, origin));
      b.rows.push_back(drives == nullptr ? row : row - static_cast<Eigen::Index>(first));
    }
  }
  if (occluder != nullptr) DarkUnits(units, *occluder, b);
  for (size_t k = 0; k < b.terms.size(); ++k) {
    RowMatrixXf& into_d = drives == nullptr ? r.diffuse : unit_d;
    RowMatrixXf& into_s = drives == nullptr ? r.specular : unit_s;
    float* d = into_d.row(b.rows[k]).data();
    float* s = into_s.row(b.rows[k]).data();
    if (occluder != nullptr) {
      AddUnitResponses<true>(b.terms[k], units, b.dark.data() + k * count, weight, d, s);
    } else {
      AddUnitResponses<false>(b.terms[k], units, nullptr, weight, d, s);
    }
  }
  if (drives != nullptr) {
    const auto at = static_cast<Eigen::Index>(first);
    r.diffuse.middleRows(at, block_rows).noalias() = unit_d * drives->diffuse;
    r.specular.middleRows(at, block_rows).noalias() = unit_s * drives->specular;
  }
}

}  // namespace

int ExposureBasis::Find(const EmitterLevels& l, float leakage_of_camera) const {
  if (leakage_of_camera != leakage) return -1;
  for (size_t k = 0; k < levels.size(); ++k) {
    const EmitterLevels& b = levels[k];
    if (b.cross.size() == l.cross.size() && b.parallel.size() == l.parallel.size() && b.cross == l.cross &&
        b.parallel == l.parallel) {
      return static_cast<int>(k);
    }
  }
  return -1;
}

float CrossLeakage(const CameraModel& camera, double leakage, double growth) {
  const double c = std::clamp(camera.optical_axis().dot(Eigen::Vector3d(0, 0, -1)), -1.0, 1.0);
  // The design axis is +z (cameras in front look along -z); sin^2 of the angle between them.
  return static_cast<float>(leakage + growth * (1 - c * c));
}

std::shared_ptr<const std::vector<Eigen::Vector3f>> CameraRays::At(double dx, double dy) {
  const std::pair<double, double> key(dx, dy);
  if (auto it = kept_.find(key); it != kept_.end()) return it->second;
  auto rays = std::make_shared<const std::vector<Eigen::Vector3f>>(camera_.PixelRays(dx, dy));
  const size_t bytes = rays->size() * sizeof(Eigen::Vector3f);
  if (kept_bytes_ + bytes <= budget_bytes_) {
    kept_.emplace(key, rays);
    kept_bytes_ += bytes;
  }
  return rays;
}

std::vector<Hit> TracePixels(CameraRays& camera_rays, const Subject& subject, int threads, double dx, double dy,
                             WorkProgress* progress) {
  const std::shared_ptr<const std::vector<Eigen::Vector3f>> rays = camera_rays.At(dx, dy);
  const Eigen::Vector3f origin = camera_rays.camera().position().cast<float>();
  std::vector<Hit> all(rays->size());
  ParallelFor(rays->size(), threads, progress, [&](size_t i) { all[i] = subject.Intersect(origin, (*rays)[i]); });
  return all;
}

std::vector<Hit> TracePixels(const CameraModel& camera, const Subject& subject, int threads, double dx, double dy,
                             WorkProgress* progress) {
  CameraRays rays(camera, /*budget_bytes=*/0);  // one call: each offset's rays freed once traced, as before
  return TracePixels(rays, subject, threads, dx, dy, progress);
}

AreaAlbedo TraceAreaAlbedo(const CameraModel& camera, const Subject& subject, int n, int threads,
                           WorkProgress* progress) {
  CameraRays rays(camera, /*budget_bytes=*/0);
  return TraceAreaAlbedo(rays, subject, n, threads, progress);
}

PixelResponses ComputeResponses(const CameraModel& camera, const Subject& subject, const Dome& dome, int threads,
                                int supersample, WorkProgress* progress, int texture_samples,
                                std::shared_ptr<const ExposureBasis> basis) {
  CameraRays rays(camera, /*budget_bytes=*/0);
  return ComputeResponses(rays, subject, dome, threads, supersample, progress, texture_samples, std::move(basis));
}

AreaAlbedo TraceAreaAlbedo(CameraRays& camera_rays, const Subject& subject, int n, int threads, WorkProgress* progress,
                           const std::vector<int32_t>* only) {
  const CameraModel& camera = camera_rays.camera();
  const size_t count = static_cast<size_t>(camera.width()) * static_cast<size_t>(camera.height());
  AreaAlbedo out;
  out.albedo.assign(count, Eigen::Vector3f::Zero());
  out.rays.assign(count, 0);
  const Eigen::Vector3f origin = camera.position().cast<float>();
  for (int sy = 0; sy < n; ++sy) {
    for (int sx = 0; sx < n; ++sx) {
      const std::shared_ptr<const std::vector<Eigen::Vector3f>> rays =
          camera_rays.At((sx + 0.5) / n - 0.5, (sy + 0.5) / n - 0.5);
      auto trace = [&](size_t i) {
        Eigen::Vector3f albedo;
        if (!subject.AlbedoAt(origin, (*rays)[i], &albedo)) return;
        out.albedo[i] += albedo;
        ++out.rays[i];
      };
      if (only == nullptr) {
        ParallelFor(rays->size(), threads, progress, trace);
      } else {
        ParallelFor(only->size(), threads, progress, [&](size_t k) { trace(static_cast<size_t>((*only)[k])); });
      }
    }
  }
  for (size_t i = 0; i < count; ++i) {
    if (out.rays[i] > 1) out.albedo[i] /= static_cast<float>(out.rays[i]);
  }
  return out;
}

namespace {

// Every ray of n x n a pixel that meets the subject, grouped by pixel: the pixels met (row-major, in order), their hits
// (a pixel's in the order of its offsets) and where each pixel's begin (pixel k's are [first[k], first[k + 1])). One
// offset's image of hits at a time: its hits are taken out before the next is traced, and no pixel has a vector of
// its own (at full scale their allocations were an eighth of a board's render).
struct PixelHits {
  std::vector<int32_t> pixels;
  std::vector<Hit> hits;
  std::vector<size_t> first;
};

PixelHits TraceHitsByPixel(CameraRays& camera_rays, const Subject& subject, int threads, int n,
                           WorkProgress* progress) {
  std::vector<std::vector<int32_t>> where;  // per offset: the pixels its rays met, in order
  std::vector<std::vector<Hit>> met;        // and what they met there
  size_t image = 0;
  for (int sy = 0; sy < n; ++sy) {
    for (int sx = 0; sx < n; ++sx) {
      const double dx = (sx + 0.5) / n - 0.5, dy = (sy + 0.5) / n - 0.5;
      const std::vector<Hit> all = TracePixels(camera_rays, subject, threads, dx, dy, progress);
      image = all.size();
      where.emplace_back();
      met.emplace_back();
      for (size_t i = 0; i < all.size(); ++i) {
        if (!all[i].hit) continue;
        where.back().push_back(static_cast<int32_t>(i));
        met.back().push_back(all[i]);
      }
    }
  }
  PixelHits out;
  size_t total = 0;
  for (const auto& m : met) total += m.size();
  out.hits.reserve(total);
  out.first.push_back(0);
  std::vector<size_t> next(where.size(), 0);  // each offset's next hit
  for (size_t i = 0; i < image; ++i) {
    for (size_t k = 0; k < where.size(); ++k) {
      if (next[k] < where[k].size() && static_cast<size_t>(where[k][next[k]]) == i)
        out.hits.push_back(met[k][next[k]++]);
    }
    if (out.hits.size() == out.first.back()) continue;
    out.pixels.push_back(static_cast<int32_t>(i));
    out.first.push_back(out.hits.size());
  }
  return out;
}

}  // namespace

PixelResponses ComputeResponses(CameraRays& camera_rays, const Subject& subject, const Dome& dome, int threads,
                                int supersample, WorkProgress* progress, int texture_samples,
                                std::shared_ptr<const ExposureBasis> basis) {
  const CameraModel& camera = camera_rays.camera();
  PixelResponses r;
  r.width = camera.width();
  r.height = camera.height();
  const Eigen::Vector3f origin = camera.position().cast<float>();
  const int n = std::max(1, supersample);
  const auto rays = static_cast<uint64_t>(r.width) * r.height * n * n;
  // The rays, then a pixel's responses for each one that hits (at most every pixel; known once traced).
  if (progress != nullptr) progress->total.store(progress->done.load() + 2 * rays);
  PixelHits met = TraceHitsByPixel(camera_rays, subject, threads, n, progress);
  r.pixels = std::move(met.pixels);
  std::vector<std::span<const Hit>> rows;
  rows.reserve(r.pixels.size());
  r.albedo.reserve(r.pixels.size());
  r.hits.reserve(r.pixels.size());
  for (size_t k = 0; k < r.pixels.size(); ++k) {
    const std::span<const Hit> row(met.hits.data() + met.first[k], met.first[k + 1] - met.first[k]);
    Eigen::Vector3f albedo = Eigen::Vector3f::Zero();
    for (const Hit& h : row) albedo += h.material.albedo;
    r.albedo.push_back(albedo / static_cast<float>(row.size()));
    r.hits.push_back(row.front());
    rows.push_back(row);
  }
  if (texture_samples > n) {
    if (progress != nullptr) {
      progress->total.fetch_add(static_cast<uint64_t>(r.pixels.size()) * texture_samples * texture_samples);
    }
    // The pixels the lighting rays met only: no other pixel's albedo is used.
    const AreaAlbedo area = TraceAreaAlbedo(camera_rays, subject, texture_samples, threads, progress, &r.pixels);
    for (size_t k = 0; k < r.pixels.size(); ++k) {
      const auto p = static_cast<size_t>(r.pixels[k]);
      if (area.rays[p] > 0) r.albedo[k] = area.albedo[p];
    }
  }
  const size_t count = rows.size();
  const size_t units = dome.units.size();
  // A convex subject shadows none of itself where the light is in front of the surface (checked below).
  const bool shadows = !subject.Convex();
  // Rows a block: kBlockHits hits, at least one row.
  const size_t block_rows = std::max<size_t>(1, kBlockHits / static_cast<size_t>(n * n));
  const size_t blocks = (count + block_rows - 1) / block_rows;
  if (progress != nullptr) progress->total.store(progress->done.load() + blocks * block_rows);
  const float weight = 1.0f / static_cast<float>(n * n);
  const UnitArrays unit_arrays(dome);
  // Left uninitialized here and zeroed a row at a time by the thread that fills it: one pass over memory the kernel
  // hands out fresh for every pose, not a single-threaded memset first (it and its page faults were 40 % of a moving
  // board's render).
  std::optional<BasisDrives> drives;
  if (basis != nullptr) drives.emplace(*basis, units);
  const size_t columns = drives ? static_cast<size_t>(drives->diffuse.cols()) : units;
  r.diffuse.resize(static_cast<Eigen::Index>(count), static_cast<Eigen::Index>(columns));
  r.specular.resize(static_cast<Eigen::Index>(count), static_cast<Eigen::Index>(columns));
  r.basis = std::move(basis);
  ParallelFor(
      blocks, threads, progress,
      [&](size_t b) {
        AddBlockResponses(rows, b * block_rows, std::min(count, (b + 1) * block_rows), origin, unit_arrays,
                          shadows ? &subject : nullptr, weight, drives ? &*drives : nullptr, r);
      },
      /*work=*/block_rows, /*min_parallel=*/2);
  return r;
}

absl::StatusOr<std::vector<float>> RenderRadianceOf(const PixelResponses& responses, const EmitterLevels& levels,
                                                    float leakage) {
  std::vector<float> rgb(static_cast<size_t>(responses.width) * responses.height * 3, 0.0f);
  if (responses.pixels.empty()) return rgb;
  Eigen::VectorXf d, s;
  if (responses.basis != nullptr) {
    const int k = responses.basis->Find(levels, leakage);
    if (k < 0) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "the responses were computed for %d exposure(s) only, and this one (leakage %g) is not among them",
          responses.basis->levels.size(), leakage));
    }
    d = responses.diffuse.col(k);
    s = responses.specular.col(k);
  } else {
    d = responses.diffuse * (levels.cross + levels.parallel);
    s = responses.specular * (levels.parallel + leakage * levels.cross);
  }
  for (size_t i = 0; i < responses.pixels.size(); ++i) {
    float* out = &rgb[static_cast<size_t>(responses.pixels[i]) * 3];
    const Eigen::Index k = static_cast<Eigen::Index>(i);
    for (int c = 0; c < 3; ++c) out[c] = 0.5f * responses.albedo[i][c] * d[k] + s[k];
  }
  return rgb;
}

std::vector<float> RenderRadiance(const PixelResponses& responses, const EmitterLevels& levels, float leakage) {
  absl::StatusOr<std::vector<float>> rgb = RenderRadianceOf(responses, levels, leakage);
  if (!rgb.ok()) {
    // Responses to every unit render any exposure; responses with a basis go through RenderRadianceOf.
    std::fprintf(stderr, "RenderRadiance: %s\n", rgb.status().ToString().c_str());
    std::abort();
  }
  return *std::move(rgb);
}

}  // namespace stage::sim
