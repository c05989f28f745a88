#include "stage/processing/texture_fusion.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <functional>
#include <limits>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "absl/strings/str_cat.h"
#include "gap_fill.h"
#include "parallel.h"
#include "stage/common/status.h"
#include "stage/common/uv_raster.h"
#include "statistics.h"

namespace stage::processing {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
// Degrees below FusionOptions::max_lobe_view_angle_deg over which a view's lobe weight fades to nothing.
constexpr double kLobeFadeDeg = 5;

bool Solved(const float* n) { return n[0] != 0 || n[1] != 0 || n[2] != 0; }

absl::Status CheckMap(const FusionView& view, const Image& map, const char* name, int channels, bool required) {
  if (map.width == 0 && !required) return absl::OkStatus();
  if (map.width != view.camera.width() || map.height != view.camera.height() || map.channels != channels ||
      map.pixels.size() != static_cast<size_t>(map.width) * map.height * channels) {
    return absl::InvalidArgumentError(absl::StrCat("texture fusion: view ", view.camera_id, ": the ", name, " map is ",
                                                   map.width, " x ", map.height, " x ", map.channels, ", not ",
                                                   view.camera.width(), " x ", view.camera.height(), " x ", channels));
  }
  return absl::OkStatus();
}

// What a view contributes at a pixel: its depth buffer and, per pixel, the weight of its edge distance (0 where the
// pixel is not usable).
struct PreparedView {
  const FusionView* view = nullptr;
  Eigen::Vector3f centre = Eigen::Vector3f::Zero();  // the camera's, stage frame
  Eigen::Vector3f axis = Eigen::Vector3f::UnitZ();   // its optical axis
  float cos_max = 0;                                 // of the options' largest view angle
  float cos_lobe_max = 0;                            // of the largest a lobe is fused from
  float cos_lobe_full = 1;                           // of the largest a lobe weighs fully at (kLobeFadeDeg less)
  std::vector<float> depth;                          // camera z of the mesh's first surface, mm
  std::vector<float> feather;                        // 0..1
};

PreparedView Prepare(const FusionView& view, const TriangleMesh& mesh, const FusionOptions& o) {
  PreparedView p;
  p.view = &view;
  p.centre = view.camera.position().cast<float>();
  p.axis = view.camera.optical_axis().cast<float>();
  p.cos_max = static_cast<float>(std::cos(o.max_view_angle_deg * M_PI / 180));
  p.cos_lobe_max = static_cast<float>(std::cos(o.max_lobe_view_angle_deg * M_PI / 180));
  p.cos_lobe_full = static_cast<float>(std::cos(std::max(0.0, o.max_lobe_view_angle_deg - kLobeFadeDeg) * M_PI / 180));
  p.depth = DepthBuffer(mesh, view.camera);
  const int w = view.camera.width(), h = view.camera.height();
  cv::Mat usable(h, w, CV_8U, cv::Scalar(0));
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const size_t i = static_cast<size_t>(y) * w + x;
      const float z = p.depth[i];
      if (z == kInf || !Solved(view.diffuse_normal.at(x, y))) continue;
      if (view.confidence.width > 0 && view.confidence.at(x, y)[0] < o.min_confidence) continue;
      // An occluding contour: a neighbour much nearer or farther (or nothing there).
      bool contour = false;
      constexpr int kDx[4] = {1, -1, 0, 0}, kDy[4] = {0, 0, 1, -1};
      for (int k = 0; k < 4; ++k) {
        const int nx = x + kDx[k], ny = y + kDy[k];
        if (nx < 0 || ny < 0 || nx >= w || ny >= h) continue;
        const float nz = p.depth[static_cast<size_t>(ny) * w + nx];
        if (nz == kInf || std::abs(nz - z) > o.contour_mm) contour = true;
      }
      if (!contour) usable.at<uint8_t>(y, x) = 1;
    }
  }
  p.feather.assign(static_cast<size_t>(w) * h, 0.0f);
  if (o.feather_px <= 0) {
    for (size_t i = 0; i < p.feather.size(); ++i) p.feather[i] = usable.data[i];
    return p;
  }
  // The distance of every usable pixel to the nearest unusable one (the image's border counts as unusable).
  cv::Mat padded;
  cv::copyMakeBorder(usable, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::Mat distance;
  cv::distanceTransform(padded, distance, cv::DIST_L2, cv::DIST_MASK_PRECISE);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const float d = distance.at<float>(y + 1, x + 1);
      p.feather[static_cast<size_t>(y) * w + x] = std::min(1.0f, d / static_cast<float>(o.feather_px));
    }
  }
  return p;
}

// The bilinear taps at (x, y) over the four nearest pixels that `use` accepts, their weights summing to 1: where a
// map is sampled (the same taps serve every map of a view).
struct Taps {
  size_t pixel[4];
  float weight[4];
  int n = 0;

  // The value of `map` (channels interleaved) at the taps.
  void Apply(const Image& map, float* out) const {
    const auto c = static_cast<size_t>(map.channels);
    std::fill(out, out + c, 0.0f);
    for (int k = 0; k < n; ++k) {
      const float* v = &map.pixels[pixel[k] * c];
      for (size_t i = 0; i < c; ++i) out[i] += weight[k] * v[i];
    }
  }
};

template <typename Use>
bool MakeTaps(int width, int height, double x, double y, Use use, Taps* taps) {
  const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
  const float fx = static_cast<float>(x - x0), fy = static_cast<float>(y - y0);
  float total = 0;
  taps->n = 0;
  for (int j = 0; j < 2; ++j) {
    for (int i = 0; i < 2; ++i) {
      const int px = x0 + i, py = y0 + j;
      if (px < 0 || py < 0 || px >= width || py >= height) continue;
      const float wgt = (i ? fx : 1 - fx) * (j ? fy : 1 - fy);
      const size_t pixel = static_cast<size_t>(py) * width + px;
      if (wgt <= 0 || !use(pixel)) continue;
      taps->pixel[taps->n] = pixel;
      taps->weight[taps->n++] = wgt;
      total += wgt;
    }
  }
  if (total <= 0) return false;
  for (int k = 0; k < taps->n; ++k) taps->weight[k] /= total;
  return true;
}

// Sums of the views' weighted samples at every texel.
struct Accumulator {
  explicit Accumulator(size_t texels)
      : albedo(3 * texels, 0),
        normal(3 * texels, 0),
        spec_normal(3 * texels, 0),
        specular(texels, 0),
        roughness(texels, 0),
        weight(texels, 0),
        spec_weight(texels, 0),
        rough_weight(texels, 0),
        spec_normal_weight(texels, 0),
        views(texels, 0) {}
  std::vector<float> albedo, normal, spec_normal, specular, roughness;
  std::vector<float> weight, spec_weight, rough_weight, spec_normal_weight;
  std::vector<uint8_t> views;  // how many views saw the texel
};

// Adds what `view` sees of the surface point `p` (normal `n`) to texel `t`; true if it saw it.
bool AddView(const PreparedView& pv, const FusionOptions& o, const Eigen::Vector3f& p, const Eigen::Vector3f& n,
             size_t t, Accumulator* acc) {
  const FusionView& v = *pv.view;
  const CameraModel& cam = v.camera;
  Eigen::Vector2d px;
  if (!cam.Project(p.cast<double>(), &px)) return false;
  const int w = cam.width(), h = cam.height();
  const int ix = static_cast<int>(std::lround(px.x())), iy = static_cast<int>(std::lround(px.y()));
  if (ix < 0 || iy < 0 || ix >= w || iy >= h) return false;
  const size_t pixel = static_cast<size_t>(iy) * w + ix;
  const float feather = pv.feather[pixel];
  if (feather <= 0) return false;
  const Eigen::Vector3f to_camera = pv.centre - p;
  const float cos_view = n.dot(to_camera.normalized());
  if (cos_view <= pv.cos_max) return false;
  const float z = -pv.axis.dot(to_camera);
  if (z > pv.depth[pixel] + static_cast<float>(o.occlusion_mm)) return false;  // something nearer hides it
  Taps taps;
  if (!MakeTaps(
          w, h, px.x(), px.y(), [&](size_t i) { return pv.feather[i] > 0; }, &taps))
    return false;
  float albedo[3], normal[3], confidence = 1;
  taps.Apply(v.albedo, albedo);
  taps.Apply(v.diffuse_normal, normal);
  if (v.confidence.width > 0) taps.Apply(v.confidence, &confidence);
  const float weight = cos_view * cos_view * std::clamp(confidence, 0.0f, 1.0f) * feather;
  if (weight <= 0) return false;
  for (int c = 0; c < 3; ++c) {
    acc->albedo[3 * t + c] += weight * albedo[c];
    acc->normal[3 * t + c] += weight * normal[c];
  }
  acc->weight[t] += weight;
  // The lobe's maps only from pixels where the view measured a lobe (its specular normal solved; a view without
  // specular normals: every pixel), or the unmeasured pixels' zeros would darken the intensity near their edge; and
  // only from a view that sees the point squarely enough for its lobe to be unbiased, faded out over the last
  // kLobeFadeDeg so that the lobe's maps do not step where a view's lobe drops out.
  if (cos_view <= pv.cos_lobe_max) return true;
  const float fade = std::min(1.0f, (cos_view - pv.cos_lobe_max) / std::max(1e-6f, pv.cos_lobe_full - pv.cos_lobe_max));
  const float lobe_weight = weight * fade * fade * (3 - 2 * fade);  // smoothstep
  Taps lobe = taps;
  if (v.specular_normal.width > 0 &&
      !MakeTaps(
          w, h, px.x(), px.y(), [&](size_t i) { return pv.feather[i] > 0 && Solved(&v.specular_normal.pixels[3 * i]); },
          &lobe)) {
    return true;
  }
  float value[3];
  if (v.specular.width > 0) {
    lobe.Apply(v.specular, value);
    acc->specular[t] += lobe_weight * value[0];
    acc->spec_weight[t] += lobe_weight;
  }
  if (v.roughness.width > 0) {
    lobe.Apply(v.roughness, value);
    acc->roughness[t] += lobe_weight * value[0];
    acc->rough_weight[t] += lobe_weight;
  }
  if (v.specular_normal.width > 0) {
    lobe.Apply(v.specular_normal, value);
    for (int c = 0; c < 3; ++c) acc->spec_normal[3 * t + c] += lobe_weight * value[c];
    acc->spec_normal_weight[t] += lobe_weight;
  }
  return true;
}

// The texel's tangent frame (columns tangent, bitangent, normal) in the mesh's frame.
Eigen::Matrix3f TexelFrame(const TriangleMesh& mesh, const UvTexel& texel, const std::vector<Eigen::Vector3f>& normals,
                           const std::vector<Eigen::Vector4f>& tangents) {
  const auto& tri = mesh.triangles[static_cast<size_t>(texel.triangle)];
  const float b[3] = {1 - texel.b1 - texel.b2, texel.b1, texel.b2};
  Eigen::Vector3f n = Eigen::Vector3f::Zero(), t = Eigen::Vector3f::Zero();
  for (int k = 0; k < 3; ++k) {
    n += b[k] * normals[static_cast<size_t>(tri[k])];
    t += b[k] * tangents[static_cast<size_t>(tri[k])].head<3>();
  }
  n.normalize();
  t = (t - n * n.dot(t)).normalized();
  const float sign = tangents[static_cast<size_t>(tri[0])].w() < 0 ? -1.0f : 1.0f;
  Eigen::Matrix3f frame;
  frame.col(0) = t;
  frame.col(1) = sign * n.cross(t);
  frame.col(2) = n;
  return frame;
}

// The mean of `sum` (channels per texel) over `weight` where it is positive; NaN elsewhere (for the dilation).
Image Mean(const std::vector<float>& sum, const std::vector<float>& weight, int size, int channels, bool unit) {
  Image out(size, size, channels);
  for (size_t t = 0; t < weight.size(); ++t) {
    float* o = &out.pixels[t * static_cast<size_t>(channels)];
    if (weight[t] <= 0) {
      std::fill(o, o + channels, kNaN);
      continue;
    }
    for (int c = 0; c < channels; ++c) o[c] = sum[t * static_cast<size_t>(channels) + c] / weight[t];
    if (unit) {
      const float norm = std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
      for (int c = 0; c < 3; ++c) o[c] = norm > 0 ? o[c] / norm : 0.0f;
    }
  }
  return out;
}

// A lobe map's local typical value at every texel (1 channel): the median of the measured texels of each
// 16 x 16-texel cell at least a quarter measured (robust to the solve's isolated bad lobes), a normalized convolution
// of the cells' medians (Gaussian, sigma 2 cells) drawn slightly towards the median over the cells (which it is far
// from every such cell; NaN if there is none), enlarged bilinearly.
std::vector<float> LocalLobeValue(const Image& image, const std::vector<uint8_t>& measured) {
  const int size = image.width;
  constexpr int kCell = 16;
  const int cells = (size + kCell - 1) / kCell;
  cv::Mat value(cells, cells, CV_32F, cv::Scalar(0)), known(cells, cells, CV_32F, cv::Scalar(0));
  std::vector<float> in_cell, medians;
  for (int cy = 0; cy < cells; ++cy) {
    for (int cx = 0; cx < cells; ++cx) {
      in_cell.clear();
      for (int y = cy * kCell; y < std::min(size, (cy + 1) * kCell); ++y) {
        for (int x = cx * kCell; x < std::min(size, (cx + 1) * kCell); ++x) {
          const size_t t = static_cast<size_t>(y) * size + x;
          if (measured[t]) in_cell.push_back(image.pixels[t]);
        }
      }
      // A cell a quarter measured or more: fewer are the scattered lobes at the edge of what the views measure.
      if (in_cell.size() * 4 < static_cast<size_t>(kCell * kCell)) continue;
      const float median = static_cast<float>(Median(in_cell));
      value.at<float>(cy, cx) = median;
      known.at<float>(cy, cx) = 1;
      medians.push_back(median);
    }
  }
  // Far from every such cell: the median over the cells (a prior of kPrior cells' weight everywhere, so the two meet
  // smoothly).
  // With no such cell (lobes measured only here and there): the median of every measured texel; NaN with none.
  if (medians.empty()) {
    for (size_t t = 0; t < measured.size(); ++t) {
      if (measured[t]) medians.push_back(image.pixels[t]);
    }
  }
  const float overall = medians.empty() ? kNaN : static_cast<float>(Median(medians));
  constexpr float kPrior = 0.05f;
  cv::GaussianBlur(value, value, cv::Size(), 2);
  cv::GaussianBlur(known, known, cv::Size(), 2);
  cv::Mat mean(cells, cells, CV_32F);
  for (int i = 0; i < cells * cells; ++i) {
    const float k = reinterpret_cast<float*>(known.data)[i];
    reinterpret_cast<float*>(mean.data)[i] =
        (reinterpret_cast<float*>(value.data)[i] + kPrior * overall) / (k + kPrior);
  }
  // Cell centres sit at (c + 0.5) * kCell - 0.5 texels: resize's half-pixel convention with a scale of kCell.
  cv::Mat full;
  cv::resize(mean, full, cv::Size(cells * kCell, cells * kCell), 0, 0, cv::INTER_LINEAR);
  std::vector<float> out(static_cast<size_t>(size) * size);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) out[static_cast<size_t>(y) * size + x] = full.at<float>(y, x);
  }
  return out;
}

// The lobe's maps (intensity, roughness, and the specular normal in the stage frame) where the views saw the surface
// but measured no lobe, or measured one whose intensity or roughness is more than kOutlier times off its
// neighbourhood's typical value (the solve's bad lobe fits: isolated specks): the normal is the diffuse one, intensity
// and roughness the neighbourhood's typical values, and the texel's specular weight 0. Returns the texels rejected.
int64_t FillLobes(const Accumulator& acc, const Image& normal, Image* spec_normal, FusedTextures* out) {
  constexpr float kOutlier = 4;
  const size_t n = acc.weight.size();
  std::vector<uint8_t> measured(n, 0);
  for (size_t t = 0; t < n; ++t) measured[t] = acc.spec_weight[t] > 0 && acc.rough_weight[t] > 0;
  out->specular_weight = Image(out->size, out->size, 1);
  out->specular_weight.pixels = acc.spec_normal_weight;
  const std::vector<float> typical_specular = LocalLobeValue(out->specular, measured);
  const std::vector<float> typical_roughness = LocalLobeValue(out->roughness, measured);
  // Judged only against a typical value there is (a NaN one rejects nothing).
  auto off = [&](float v, float typical) {
    return std::isfinite(typical) && !(v >= typical / kOutlier && v <= typical * kOutlier);
  };
  int64_t rejected = 0;
  for (size_t t = 0; t < n; ++t) {
    if (acc.weight[t] <= 0) continue;
    float& specular = out->specular.pixels[t];
    float& roughness = out->roughness.pixels[t];
    if (measured[t] && (off(specular, typical_specular[t]) || off(roughness, typical_roughness[t]))) {
      measured[t] = 0;
      ++rejected;
      out->specular_weight.pixels[t] = 0;
    }
    if (!measured[t]) {
      specular = typical_specular[t];
      roughness = typical_roughness[t];
    }
    if (out->specular_weight.pixels[t] <= 0) std::copy_n(&normal.pixels[3 * t], 3, &spec_normal->pixels[3 * t]);
  }
  return rejected;
}

// Grows the set texels `passes` rings (the mean of set neighbours), renormalizes unit vectors, zeroes what is left.
void Dilate(Image* image, int passes, bool unit) {
  GrowIntoGaps(image->width, image->height, image->channels, passes, GapGrowth::kMean, &image->pixels);
  const auto c = static_cast<size_t>(image->channels);
  for (size_t i = 0; i < image->pixels.size(); i += c) {
    float* o = &image->pixels[i];
    if (o[0] != o[0]) {
      std::fill(o, o + c, 0.0f);
    } else if (unit) {
      const float norm = std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
      for (size_t k = 0; k < 3; ++k) o[k] = norm > 0 ? o[k] / norm : 0.0f;
    }
  }
}

// Normals (stage frame, per texel; NaN where empty, as wherever no triangle covers the texel: the diffuse and the
// specular) in the head's frame and in each texel's tangent frame (computed once for both); NaN where empty.
struct ExpressedNormals {
  Image object, tangent;
};
void ExpressNormals(const std::vector<const Image*>& stage_normals, const std::vector<UvTexel>& texels,
                    const TriangleMesh& mesh, const std::vector<Eigen::Vector3f>& vertex_normals,
                    const std::vector<Eigen::Vector4f>& tangents, const Eigen::Matrix3f& head_from_stage,
                    const std::vector<ExpressedNormals*>& out) {
  const int size = stage_normals[0]->width;
  for (ExpressedNormals* e : out) e->object = e->tangent = Image(size, size, 3);
  internal::ParallelRows(size, 0, [&](int y0, int y1) {
    for (size_t t = static_cast<size_t>(y0) * size; t < static_cast<size_t>(y1) * size; ++t) {
      std::optional<Eigen::Matrix3f> frame;
      for (size_t k = 0; k < stage_normals.size(); ++k) {
        const float* s = &stage_normals[k]->pixels[3 * t];
        float* object = &out[k]->object.pixels[3 * t];
        float* tangent = &out[k]->tangent.pixels[3 * t];
        if (s[0] != s[0]) {
          std::fill_n(object, 3, kNaN);
          std::fill_n(tangent, 3, kNaN);
          continue;
        }
        if (!frame) frame = TexelFrame(mesh, texels[t], vertex_normals, tangents).transpose();
        const Eigen::Vector3f n(s[0], s[1], s[2]);
        const Eigen::Vector3f o = head_from_stage * n, ts = *frame * n;
        for (int c = 0; c < 3; ++c) {
          object[c] = o[c];
          tangent[c] = ts[c];
        }
      }
    }
  });
}

// +1 if the mesh's normals (its winding) point the way the views' normals do, -1 if they point into the surface: a
// vote over every 16th covered texel of the views that see it unhidden.
float Orientation(const std::vector<UvTexel>& texels, const std::vector<Eigen::Vector3f>& points,
                  const std::vector<Eigen::Vector3f>& normals, const std::vector<PreparedView>& views,
                  const FusionOptions& o) {
  double vote = 0;
  for (size_t t = 0; t < texels.size(); t += 16) {
    if (!texels[t].covered()) continue;
    for (const PreparedView& pv : views) {
      const CameraModel& cam = pv.view->camera;
      Eigen::Vector2d px;
      if (!cam.Project(points[t].cast<double>(), &px)) continue;
      const int ix = static_cast<int>(std::lround(px.x())), iy = static_cast<int>(std::lround(px.y()));
      if (ix < 0 || iy < 0 || ix >= cam.width() || iy >= cam.height()) continue;
      const size_t pixel = static_cast<size_t>(iy) * cam.width() + ix;
      const float z = (cam.rotation().cast<float>() * (points[t] - cam.position().cast<float>())).z();
      if (pv.feather[pixel] <= 0 || z > pv.depth[pixel] + static_cast<float>(o.occlusion_mm)) continue;
      const float* n = pv.view->diffuse_normal.at(ix, iy);
      vote += normals[t].dot(Eigen::Vector3f(n[0], n[1], n[2])) > 0 ? 1 : -1;
    }
  }
  return vote < 0 ? -1.0f : 1.0f;
}

}  // namespace

absl::Status FusionOptions::Validate() const {
  auto bad = [](const std::string& what) { return absl::InvalidArgumentError(absl::StrCat("texture fusion: ", what)); };
  if (size < 16 || size > 16384) return bad(absl::StrCat("size ", size, " is not in 16..16384"));
  if (part < -1 || part > 255) return bad(absl::StrCat("part ", part, " is not -1 (every part) or a part"));
  if (!(max_view_angle_deg >= 1 && max_view_angle_deg <= 89)) {
    return bad(absl::StrCat("max_view_angle_deg ", max_view_angle_deg, " is not in 1..89"));
  }
  if (!(max_lobe_view_angle_deg >= 1 && max_lobe_view_angle_deg <= 89)) {
    return bad(absl::StrCat("max_lobe_view_angle_deg ", max_lobe_view_angle_deg, " is not in 1..89"));
  }
  if (!(min_confidence >= 0 && min_confidence <= 1)) {
    return bad(absl::StrCat("min_confidence ", min_confidence, " is not in 0..1"));
  }
  if (!(feather_px >= 0 && feather_px <= 256)) return bad(absl::StrCat("feather_px ", feather_px, " is not in 0..256"));
  if (!(occlusion_mm > 0)) return bad(absl::StrCat("occlusion_mm ", occlusion_mm, " is not above 0"));
  if (!(contour_mm > 0)) return bad(absl::StrCat("contour_mm ", contour_mm, " is not above 0"));
  if (dilation_px < 0 || dilation_px > 64) return bad(absl::StrCat("dilation_px ", dilation_px, " is not in 0..64"));
  return absl::OkStatus();
}

std::vector<Eigen::Vector4f> VertexTangents(const TriangleMesh& mesh, const std::vector<Eigen::Vector3f>& normals) {
  const size_t n = mesh.positions.size();
  std::vector<Eigen::Vector3f> tan(n, Eigen::Vector3f::Zero()), bitan(n, Eigen::Vector3f::Zero());
  for (const auto& tri : mesh.triangles) {
    const Eigen::Vector3f e1 = mesh.positions[tri[1]] - mesh.positions[tri[0]];
    const Eigen::Vector3f e2 = mesh.positions[tri[2]] - mesh.positions[tri[0]];
    const Eigen::Vector2f d1 = mesh.uvs[tri[1]] - mesh.uvs[tri[0]], d2 = mesh.uvs[tri[2]] - mesh.uvs[tri[0]];
    const float det = d1.x() * d2.y() - d2.x() * d1.y();
    if (std::abs(det) < 1e-12f) continue;
    // dP/du and dP/dv of the triangle, times its UV area (twice): larger triangles weigh more.
    const Eigen::Vector3f t = (e1 * d2.y() - e2 * d1.y()) * (det > 0 ? 1.0f : -1.0f);
    const Eigen::Vector3f b = (e2 * d1.x() - e1 * d2.x()) * (det > 0 ? 1.0f : -1.0f);
    for (int k = 0; k < 3; ++k) {
      tan[static_cast<size_t>(tri[k])] += t;
      bitan[static_cast<size_t>(tri[k])] += b;
    }
  }
  std::vector<Eigen::Vector4f> out(n);
  for (size_t v = 0; v < n; ++v) {
    const Eigen::Vector3f& nv = normals[v];
    Eigen::Vector3f t = tan[v] - nv * nv.dot(tan[v]);
    if (t.squaredNorm() < 1e-20f) {
      // No UV gradient here: any direction in the tangent plane.
      t = nv.unitOrthogonal();
    }
    t.normalize();
    const float sign = nv.cross(t).dot(bitan[v]) < 0 ? -1.0f : 1.0f;
    out[v] << t, sign;
  }
  return out;
}

std::vector<float> DepthBuffer(const TriangleMesh& mesh, const CameraModel& camera) {
  const int w = camera.width(), h = camera.height();
  std::vector<float> depth(static_cast<size_t>(w) * h, kInf);
  const size_t n = mesh.positions.size();
  std::vector<Eigen::Vector2f> px(n);
  std::vector<float> z(n);
  std::vector<bool> ok(n);
  const Eigen::Matrix3f rot = camera.rotation().cast<float>();
  const Eigen::Vector3f centre = camera.position().cast<float>();
  for (size_t v = 0; v < n; ++v) {
    z[v] = (rot * (mesh.positions[v] - centre)).z();
    Eigen::Vector2d p;
    ok[v] = z[v] > 1.0f && camera.Project(mesh.positions[v].cast<double>(), &p);
    px[v] = p.cast<float>();
  }
  for (const auto& tri : mesh.triangles) {
    if (!ok[tri[0]] || !ok[tri[1]] || !ok[tri[2]]) continue;
    const Eigen::Vector2f &a = px[tri[0]], &b = px[tri[1]], &c = px[tri[2]];
    const float area = (b - a).x() * (c - a).y() - (c - a).x() * (b - a).y();
    if (std::abs(area) < 1e-12f) continue;
    const int x0 = std::max(0, static_cast<int>(std::ceil(std::min({a.x(), b.x(), c.x()}))));
    const int x1 = std::min(w - 1, static_cast<int>(std::floor(std::max({a.x(), b.x(), c.x()}))));
    const int y0 = std::max(0, static_cast<int>(std::ceil(std::min({a.y(), b.y(), c.y()}))));
    const int y1 = std::min(h - 1, static_cast<int>(std::floor(std::max({a.y(), b.y(), c.y()}))));
    // 1 / z is linear across a triangle's image (perspective-correct depth).
    const float iz[3] = {1 / z[tri[0]], 1 / z[tri[1]], 1 / z[tri[2]]};
    for (int y = y0; y <= y1; ++y) {
      for (int x = x0; x <= x1; ++x) {
        const Eigen::Vector2f p(static_cast<float>(x), static_cast<float>(y));
        const float w1 = ((p - a).x() * (c - a).y() - (c - a).x() * (p - a).y()) / area;
        const float w2 = ((b - a).x() * (p - a).y() - (p - a).x() * (b - a).y()) / area;
        const float w0 = 1 - w1 - w2;
        if (w0 < 0 || w1 < 0 || w2 < 0) continue;
        const float d = 1 / (w0 * iz[0] + w1 * iz[1] + w2 * iz[2]);
        float& cell = depth[static_cast<size_t>(y) * w + x];
        cell = std::min(cell, d);
      }
    }
  }
  return depth;
}

namespace {

absl::Status CheckInputs(const TriangleMesh& mesh, const std::vector<FusionView>& views) {
  if (mesh.uvs.size() != mesh.positions.size()) {
    return absl::InvalidArgumentError("texture fusion: the mesh has no texture coordinate per vertex");
  }
  for (const FusionView& v : views) {
    STAGE_RETURN_IF_ERROR(CheckMap(v, v.albedo, "albedo", 3, true));
    STAGE_RETURN_IF_ERROR(CheckMap(v, v.diffuse_normal, "diffuse normal", 3, true));
    STAGE_RETURN_IF_ERROR(CheckMap(v, v.specular, "specular", 1, false));
    STAGE_RETURN_IF_ERROR(CheckMap(v, v.roughness, "roughness", 1, false));
    STAGE_RETURN_IF_ERROR(CheckMap(v, v.specular_normal, "specular normal", 3, false));
    STAGE_RETURN_IF_ERROR(CheckMap(v, v.confidence, "confidence", 1, false));
  }
  return absl::OkStatus();
}

// The surface at every texel of the layout: where it is and its (outward-turned) normal, and per vertex the normals
// and tangent frames.
struct TexelSurface {
  std::vector<UvTexel> texels;
  std::vector<Eigen::Vector3f> points, normals;
  std::vector<Eigen::Vector3f> vertex_normals;
  std::vector<Eigen::Vector4f> tangents;
};

TexelSurface SurfaceAtTexels(const TriangleMesh& mesh, const std::vector<PreparedView>& prepared,
                             const FusionOptions& options) {
  TexelSurface s;
  s.texels = RasterizeUv(mesh, options.size, options.part);
  s.vertex_normals = mesh.VertexNormals();
  const Eigen::Vector3f none(kNaN, kNaN, kNaN);
  s.points = InterpolateAtTexels(mesh, s.texels, mesh.positions, none);
  s.normals = InterpolateAtTexels(mesh, s.texels, s.vertex_normals, none);
  // Meshes come wound either way (the OBJ format does not say which side is out): the normals are turned to face
  // where the views' normals do.
  if (Orientation(s.texels, s.points, s.normals, prepared, options) < 0) {
    for (auto& n : s.vertex_normals) n = -n;
    for (auto& n : s.normals) n = -n;
  }
  s.tangents = VertexTangents(mesh, s.vertex_normals);
  return s;
}

// Every view's weighted samples summed at every texel; the texels each view saw into `counts`.
Accumulator Accumulate(const TexelSurface& s, const std::vector<PreparedView>& prepared, const FusionOptions& options,
                       std::vector<int64_t>* counts) {
  const int size = options.size;
  Accumulator acc(s.texels.size());
  std::vector<std::atomic<int64_t>> seen(prepared.size());
  internal::ParallelRows(size, 0, [&](int y0, int y1) {
    std::vector<int64_t> local(prepared.size(), 0);
    for (int y = y0; y < y1; ++y) {
      for (int x = 0; x < size; ++x) {
        const size_t t = static_cast<size_t>(y) * size + x;
        if (!s.texels[t].covered()) continue;
        const Eigen::Vector3f n = s.normals[t].normalized();
        for (size_t v = 0; v < prepared.size(); ++v) {
          if (!AddView(prepared[v], options, s.points[t], n, t, &acc)) continue;
          ++local[v];
          acc.views[t] = static_cast<uint8_t>(std::min(255, acc.views[t] + 1));
        }
      }
    }
    for (size_t v = 0; v < prepared.size(); ++v) seen[v] += local[v];
  });
  counts->clear();
  for (auto& c : seen) counts->push_back(c.load());
  return acc;
}

// The sums' means as textures: normals in the head's frame and in tangent space where views saw the surface, then
// every texture grown past the covered texels (a grown texel has no frame of its own: its tangent-space normal is its
// neighbours' mean).
void MakeTextures(const Accumulator& acc, const TexelSurface& s, const TriangleMesh& mesh,
                  const Eigen::Isometry3f& head_from_stage, const FusionOptions& options, FusedTextures* out) {
  const int size = options.size;
  out->size = size;
  Image normal, spec_normal;
  const std::vector<std::function<void()>> means = {
      [&] { out->albedo = Mean(acc.albedo, acc.weight, size, 3, false); },
      [&] { out->specular = Mean(acc.specular, acc.spec_weight, size, 1, false); },
      [&] { out->roughness = Mean(acc.roughness, acc.rough_weight, size, 1, false); },
      [&] { normal = Mean(acc.normal, acc.weight, size, 3, true); },
      [&] { spec_normal = Mean(acc.spec_normal, acc.spec_normal_weight, size, 3, true); }};
  internal::ParallelItems(static_cast<int>(means.size()), 0, [&](int i) { means[static_cast<size_t>(i)](); });
  out->lobes_rejected = FillLobes(acc, normal, &spec_normal, out);
  ExpressedNormals diffuse, specular;
  ExpressNormals({&normal, &spec_normal}, s.texels, mesh, s.vertex_normals, s.tangents, head_from_stage.linear(),
                 {&diffuse, &specular});
  out->normal_object = std::move(diffuse.object);
  out->normal_tangent = std::move(diffuse.tangent);
  out->specular_normal_object = std::move(specular.object);
  out->specular_normal_tangent = std::move(specular.tangent);
  const std::vector<std::pair<Image*, bool>> grown = {{&out->albedo, false},
                                                      {&out->specular, false},
                                                      {&out->roughness, false},
                                                      {&out->normal_object, true},
                                                      {&out->normal_tangent, true},
                                                      {&out->specular_normal_object, true},
                                                      {&out->specular_normal_tangent, true}};
  internal::ParallelItems(static_cast<int>(grown.size()), 0, [&](int i) {
    Dilate(grown[static_cast<size_t>(i)].first, options.dilation_px, grown[static_cast<size_t>(i)].second);
  });
  out->state.assign(s.texels.size(), TexelState::kEmpty);
  for (size_t t = 0; t < s.texels.size(); ++t) {
    if (acc.weight[t] > 0) {
      out->state[t] = TexelState::kCovered;
    } else if (Solved(&out->normal_object.pixels[3 * t])) {
      out->state[t] = TexelState::kDilated;
    }
  }
  out->weight = Image(size, size, 1);
  out->weight.pixels = acc.weight;
  out->views = acc.views;
}

}  // namespace

absl::StatusOr<FusedTextures> FuseTextures(const TriangleMesh& mesh, const Eigen::Isometry3f& head_from_stage,
                                           const std::vector<FusionView>& views, const FusionOptions& options) {
  STAGE_RETURN_IF_ERROR(options.Validate());
  STAGE_RETURN_IF_ERROR(CheckInputs(mesh, views));
  std::vector<PreparedView> prepared(views.size());
  internal::ParallelItems(static_cast<int>(views.size()), 0,
                          [&](int i) { prepared[static_cast<size_t>(i)] = Prepare(views[i], mesh, options); });
  const TexelSurface surface = SurfaceAtTexels(mesh, prepared, options);
  FusedTextures out;
  const Accumulator acc = Accumulate(surface, prepared, options, &out.texels_per_view);
  MakeTextures(acc, surface, mesh, head_from_stage, options, &out);
  return out;
}

absl::StatusOr<TextureErrors> CompareTextures(const FusedTextures& fused, const FusedTextures& truth,
                                              const std::vector<bool>* mask) {
  const size_t n = static_cast<size_t>(fused.size) * static_cast<size_t>(fused.size);
  if (fused.size != truth.size || fused.state.size() != n || truth.state.size() != n ||
      fused.specular_weight.pixels.size() != n || truth.specular_weight.pixels.size() != n ||
      (mask != nullptr && mask->size() != n)) {
    return absl::InvalidArgumentError(absl::StrCat("compare textures: sizes ", fused.size, " and ", truth.size,
                                                   " (or a state or mask of another size)"));
  }
  std::vector<double> albedo, normal, spec_normal, specular;
  double roughness = 0;
  auto angle = [](const float* a, const float* b) {
    return AngleDeg(Eigen::Vector3d(a[0], a[1], a[2]), Eigen::Vector3d(b[0], b[1], b[2]));
  };
  for (size_t t = 0; t < n; ++t) {
    if (fused.state[t] != TexelState::kCovered || truth.state[t] != TexelState::kCovered) continue;
    if (mask != nullptr && !(*mask)[t]) continue;
    const float *a = &fused.albedo.pixels[3 * t], *ta = &truth.albedo.pixels[3 * t];
    if (ta[0] <= 0 || ta[1] <= 0 || ta[2] <= 0) continue;
    double rel = 0;
    for (int c = 0; c < 3; ++c) rel += std::abs(a[c] / ta[c] - 1) / 3;
    albedo.push_back(rel);
    normal.push_back(angle(&fused.normal_object.pixels[3 * t], &truth.normal_object.pixels[3 * t]));
    const float *s = &fused.specular_normal_object.pixels[3 * t], *ts = &truth.specular_normal_object.pixels[3 * t];
    if (fused.specular_weight.pixels[t] <= 0 || truth.specular_weight.pixels[t] <= 0) continue;
    spec_normal.push_back(angle(s, ts));
    if (truth.specular.pixels[t] > 0)
      specular.push_back(std::abs(fused.specular.pixels[t] / truth.specular.pixels[t] - 1));
    roughness += std::abs(fused.roughness.pixels[t] - truth.roughness.pixels[t]);
  }
  auto mean = [](const std::vector<double>& v) {
    double sum = 0;
    for (double x : v) sum += x;
    return v.empty() ? 0.0 : sum / static_cast<double>(v.size());
  };
  TextureErrors e;
  e.texels = static_cast<int64_t>(albedo.size());
  e.albedo_mean = mean(albedo);
  e.albedo_median = Median(albedo);
  e.normal_mean_deg = mean(normal);
  e.normal_median_deg = Median(normal);
  e.normal_p90_deg = Quantile(normal, 9, 10);
  e.specular_texels = static_cast<int64_t>(spec_normal.size());
  e.specular_normal_mean_deg = mean(spec_normal);
  e.specular_normal_median_deg = Median(spec_normal);
  if (!spec_normal.empty()) {
    e.specular_median = Median(specular);
    e.roughness_mean = roughness / static_cast<double>(spec_normal.size());
  }
  return e;
}

}  // namespace stage::processing
