// Multi-view stereo's depth maps (mvs_internal.h). Each view is matched against its neighbours by a sweep along the
// depth of every pixel: a depth puts the pixel's point at a place in each neighbour's (undistorted) image, on its
// epipolar line (pixel = a + z * H x, dehomogenized: the pair's geometry, as a rectified pair's disparity is), and the
// neighbour's image sampled there is compared with the view's own over a window by zero-mean normalized
// cross-correlation. Coarse to fine: the coarsest level of a Gaussian pyramid sweeps the head's whole volume in steps
// of a pixel; every finer level sweeps a few steps about the coarser level's depth. The best depth is refined to a
// fraction of a step by a parabola through its neighbours' scores.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "mvs_internal.h"
#include "statistics.h"

namespace stage::processing {
namespace {

constexpr double kPi = 3.14159265358979323846;

// One level of a view's pyramid: the image and its pinhole intrinsics at that level.
struct Level {
  cv::Mat grey;  // CV_32F
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
};

// A Gaussian pyramid: level 0 is the view; level l + 1 is cv::pyrDown of level l (its pixel i sits on pixel 2i).
std::vector<Level> BuildPyramid(const MvsView& v, int levels) {
  std::vector<Level> out(levels);
  out[0].grey = cv::Mat(v.height, v.width, CV_32F, const_cast<float*>(v.grey.data())).clone();
  out[0].width = v.width;
  out[0].height = v.height;
  out[0].fx = v.fx, out[0].fy = v.fy, out[0].cx = v.cx, out[0].cy = v.cy;
  for (int l = 1; l < levels; ++l) {
    cv::pyrDown(out[l - 1].grey, out[l].grey);
    Level& L = out[l];
    L.width = L.grey.cols;
    L.height = L.grey.rows;
    L.fx = out[l - 1].fx / 2, L.fy = out[l - 1].fy / 2, L.cx = out[l - 1].cx / 2, L.cy = out[l - 1].cy / 2;
  }
  return out;
}

Eigen::Matrix3d Intrinsics(const Level& L) {
  Eigen::Matrix3d K;
  K << L.fx, 0, L.cx, 0, L.fy, L.cy, 0, 0, 1;
  return K;
}

// Where a depth z of reference pixel x lands in a neighbour, homogeneous: a + z * (H x).
struct PairWarp {
  Eigen::Vector3d a;
  Eigen::Matrix3d h;
};

PairWarp MakeWarp(const MvsView& ref, const Level& rl, const MvsView& nb, const Level& nl) {
  // X = C_r + z R_r^T K_r^-1 x (z along the reference's axis); in the neighbour: K_n R_n (X - C_n).
  const Eigen::Matrix3d kn = Intrinsics(nl);
  PairWarp w;
  w.a = kn * nb.rotation * (ref.position - nb.position);
  w.h = kn * nb.rotation * ref.rotation.transpose() * Intrinsics(rl).inverse();
  return w;
}

// Pixels the neighbour's point moves per mm of depth at z.
double PixelsPerMm(const PairWarp& w, const Eigen::Vector3d& hx, double z) {
  const Eigen::Vector3d p = w.a + z * hx;
  if (p.z() <= 0) return 0;
  // d/dz (p.xy / p.z) = (hx.xy p.z - p.xy hx.z) / p.z^2
  const Eigen::Vector2d d = (hx.head<2>() * p.z() - p.head<2>() * hx.z()) / (p.z() * p.z());
  return d.norm();
}

// The depths a level sweeps: per pixel z0 + k * step for k in [first, first + count); step 0: none.
struct Hypotheses {
  std::vector<float> z0, step;
  int first = 0, count = 0;
};

float Bilinear(const cv::Mat& img, double u, double v) {
  const int x0 = static_cast<int>(u), y0 = static_cast<int>(v);
  const float fx = static_cast<float>(u - x0), fy = static_cast<float>(v - y0);
  const float* r0 = img.ptr<float>(y0);
  const float* r1 = img.ptr<float>(y0 + 1);
  return (1 - fy) * ((1 - fx) * r0[x0] + fx * r0[x0 + 1]) + fy * ((1 - fx) * r1[x0] + fx * r1[x0 + 1]);
}

cv::Mat BoxMean(const cv::Mat& m, int window) {
  cv::Mat out;
  cv::boxFilter(m, out, CV_32F, cv::Size(window, window), cv::Point(-1, -1), true, cv::BORDER_REFLECT);
  return out;
}

// The reference's window statistics at a level.
struct RefStats {
  cv::Mat mean, var;
  cv::Mat foreground;  // CV_8U: signal and texture enough to match
};

RefStats MakeRefStats(const Level& L, float min_signal, int window) {
  RefStats s;
  s.mean = BoxMean(L.grey, window);
  s.var = BoxMean(L.grey.mul(L.grey), window) - s.mean.mul(s.mean);
  s.foreground = cv::Mat(L.height, L.width, CV_8U);
  for (int y = 0; y < L.height; ++y) {
    const float* g = L.grey.ptr<float>(y);
    const float* m = s.mean.ptr<float>(y);
    const float* v = s.var.ptr<float>(y);
    uint8_t* f = s.foreground.ptr<uint8_t>(y);
    // Texture: a window's contrast of at least 0.5 % of its mean.
    for (int x = 0; x < L.width; ++x) f[x] = g[x] >= min_signal && v[x] > 2.5e-5f * m[x] * m[x];
  }
  return s;
}

// The correlation of the reference with neighbour `nl` warped to depth z0 + k * step, per pixel (-1: none).
cv::Mat ScoreAgainst(const Level& rl, const RefStats& rs, const Level& nl, const PairWarp& w, const Hypotheses& h,
                     int k, int window) {
  cv::Mat warped(rl.height, rl.width, CV_32F, cv::Scalar(0)), inside(rl.height, rl.width, CV_8U, cv::Scalar(0));
  const double umax = nl.width - 1.001, vmax = nl.height - 1.001;
  for (int y = 0; y < rl.height; ++y) {
    float* out = warped.ptr<float>(y);
    uint8_t* in = inside.ptr<uint8_t>(y);
    const uint8_t* fg = rs.foreground.ptr<uint8_t>(y);
    const size_t row = static_cast<size_t>(y) * rl.width;
    for (int x = 0; x < rl.width; ++x) {
      const float step = h.step[row + x];
      if (step <= 0 || !fg[x]) continue;
      const double z = h.z0[row + x] + (h.first + k) * step;
      const Eigen::Vector3d p = w.a + z * (w.h * Eigen::Vector3d(x, y, 1));
      if (p.z() <= 0) continue;
      const double u = p.x() / p.z(), v = p.y() / p.z();
      if (!(u >= 0 && v >= 0 && u < umax && v < vmax)) continue;
      out[x] = Bilinear(nl.grey, u, v);
      in[x] = 1;
    }
  }
  const cv::Mat mw = BoxMean(warped, window);
  const cv::Mat vw = BoxMean(warped.mul(warped), window) - mw.mul(mw);
  const cv::Mat mrw = BoxMean(rl.grey.mul(warped), window);
  cv::Mat score(rl.height, rl.width, CV_32F, cv::Scalar(-1));
  for (int y = 0; y < rl.height; ++y) {
    const uint8_t* in = inside.ptr<uint8_t>(y);
    const float *a = mw.ptr<float>(y), *b = vw.ptr<float>(y), *c = mrw.ptr<float>(y);
    const float *mr = rs.mean.ptr<float>(y), *vr = rs.var.ptr<float>(y);
    float* s = score.ptr<float>(y);
    for (int x = 0; x < rl.width; ++x) {
      if (!in[x] || b[x] <= 1e-12f) continue;
      s[x] = (c[x] - mr[x] * a[x]) / std::sqrt(vr[x] * b[x]);
    }
  }
  return score;
}

// The mean of the best `best_of` of `scores` per pixel.
cv::Mat BestOf(const std::vector<cv::Mat>& scores, int best_of) {
  const int rows = scores[0].rows, cols = scores[0].cols, n = static_cast<int>(scores.size());
  const int take = std::min(best_of, n);
  cv::Mat out(rows, cols, CV_32F);
  std::vector<float> v(n);
  for (int y = 0; y < rows; ++y) {
    float* o = out.ptr<float>(y);
    for (int x = 0; x < cols; ++x) {
      for (int i = 0; i < n; ++i) v[i] = scores[i].ptr<float>(y)[x];
      std::partial_sort(v.begin(), v.begin() + take, v.end(), std::greater<float>());
      float sum = 0;
      for (int i = 0; i < take; ++i) sum += v[i];
      o[x] = sum / static_cast<float>(take);
    }
  }
  return out;
}

// Per pixel the best hypothesis, refined by a parabola through its neighbours' scores; boundary bests count only
// where `keep_boundary` (a coarser level's depth off by more than the range: the next level looks again).
void PickBest(const std::vector<cv::Mat>& cost, const Hypotheses& h, double min_score, bool keep_boundary,
              DepthMap* out) {
  const int rows = cost[0].rows, cols = cost[0].cols, n = h.count;
  out->width = cols;
  out->height = rows;
  out->depth.assign(static_cast<size_t>(rows) * cols, 0.f);
  out->score.assign(out->depth.size(), -1.f);
  for (int y = 0; y < rows; ++y) {
    for (int x = 0; x < cols; ++x) {
      const size_t i = static_cast<size_t>(y) * cols + x;
      if (h.step[i] <= 0) continue;
      int best = 0;
      float bs = cost[0].ptr<float>(y)[x];
      for (int k = 1; k < n; ++k) {
        const float s = cost[k].ptr<float>(y)[x];
        if (s > bs) bs = s, best = k;
      }
      if (bs < min_score) continue;
      double offset = 0;
      if (best > 0 && best < n - 1) {
        const double a = cost[best - 1].ptr<float>(y)[x], c = cost[best + 1].ptr<float>(y)[x];
        const double curv = a - 2 * bs + c;
        if (curv < 0) offset = std::clamp(0.5 * (a - c) / curv, -0.5, 0.5);
      } else if (!keep_boundary) {
        continue;
      }
      out->depth[i] = static_cast<float>(h.z0[i] + (h.first + best + offset) * h.step[i]);
      out->score[i] = bs;
    }
  }
}

// The coarsest level's hypotheses: every pixel's ray through the head's volume, in steps that move the point by at
// most a pixel in any neighbour.
Hypotheses VolumeSweep(const MvsView& ref, const Level& rl, const std::vector<PairWarp>& warps, const MvsOptions& o) {
  Hypotheses h;
  const size_t n = static_cast<size_t>(rl.width) * rl.height;
  h.z0.assign(n, 0.f);
  h.step.assign(n, 0.f);
  std::vector<float> z1(n, 0.f);
  const Eigen::Matrix3d to_ray = ref.rotation.transpose() * Intrinsics(rl).inverse();
  const Eigen::Vector3d oc = ref.position - o.volume_centre_mm;
  double steps = 2;
  for (int y = 0; y < rl.height; ++y) {
    for (int x = 0; x < rl.width; ++x) {
      // |oc + z d|^2 = r^2, d with a unit component along the axis: z is the depth.
      const Eigen::Vector3d d = to_ray * Eigen::Vector3d(x, y, 1);
      const double a = d.squaredNorm(), b = 2 * oc.dot(d),
                   c = oc.squaredNorm() - o.volume_radius_mm * o.volume_radius_mm;
      const double disc = b * b - 4 * a * c;
      if (disc <= 0) continue;
      const double zn = std::max(1.0, (-b - std::sqrt(disc)) / (2 * a)), zf = (-b + std::sqrt(disc)) / (2 * a);
      if (zf <= zn) continue;
      const size_t i = static_cast<size_t>(y) * rl.width + x;
      h.z0[i] = static_cast<float>(zn);
      z1[i] = static_cast<float>(zf);
      double rate = 0;
      for (const PairWarp& w : warps) rate = std::max(rate, PixelsPerMm(w, Eigen::Vector3d(x, y, 1), 0.5 * (zn + zf)));
      steps = std::max(steps, std::ceil((zf - zn) * rate) + 1);
    }
  }
  h.count = static_cast<int>(std::min(steps, 4096.0));
  for (size_t i = 0; i < n; ++i) {
    if (z1[i] > 0) h.step[i] = (z1[i] - h.z0[i]) / static_cast<float>(h.count - 1);
  }
  return h;
}

// A finer level's hypotheses about `prior` (the coarser level's depth, upsampled and its holes filled).
Hypotheses RefineSweep(const Level& rl, const std::vector<float>& prior, const std::vector<PairWarp>& warps,
                       int refine_steps) {
  Hypotheses h;
  h.z0 = prior;
  h.step.assign(prior.size(), 0.f);
  h.first = -refine_steps;
  h.count = 2 * refine_steps + 1;
  for (int y = 0; y < rl.height; ++y) {
    for (int x = 0; x < rl.width; ++x) {
      const size_t i = static_cast<size_t>(y) * rl.width + x;
      if (prior[i] <= 0) continue;
      double rate = 0;
      for (const PairWarp& w : warps) rate = std::max(rate, PixelsPerMm(w, Eigen::Vector3d(x, y, 1), prior[i]));
      if (rate > 0) h.step[i] = static_cast<float>(1 / rate);
    }
  }
  return h;
}

// The coarser level's depth at this level's pixels (pixel i of the coarser sits on pixel 2i): bilinear over its
// depths where all four are known, the nearest known otherwise; then holes of the foreground filled from their
// neighbours, a few pixels deep.
std::vector<float> Upsample(const DepthMap& coarse, const Level& fine, const cv::Mat& foreground) {
  std::vector<float> out(static_cast<size_t>(fine.width) * fine.height, 0.f);
  auto at = [&](int x, int y) { return coarse.depth[static_cast<size_t>(y) * coarse.width + x]; };
  for (int y = 0; y < fine.height; ++y) {
    for (int x = 0; x < fine.width; ++x) {
      const double u = std::min(x * 0.5, coarse.width - 1.0), v = std::min(y * 0.5, coarse.height - 1.0);
      const int x0 = static_cast<int>(u), y0 = static_cast<int>(v);
      const int x1 = std::min(x0 + 1, coarse.width - 1), y1 = std::min(y0 + 1, coarse.height - 1);
      const double fx = u - x0, fy = v - y0;
      const float d[4] = {at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1)};
      const double w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
      double sum = 0, weight = 0;
      for (int k = 0; k < 4; ++k) {
        if (d[k] > 0 && w[k] > 0) sum += w[k] * d[k], weight += w[k];
      }
      if (weight > 0) out[static_cast<size_t>(y) * fine.width + x] = static_cast<float>(sum / weight);
    }
  }
  for (int pass = 0; pass < 4; ++pass) {
    std::vector<float> next = out;
    for (int y = 0; y < fine.height; ++y) {
      for (int x = 0; x < fine.width; ++x) {
        const size_t i = static_cast<size_t>(y) * fine.width + x;
        if (out[i] > 0 || !foreground.ptr<uint8_t>(y)[x]) continue;
        double sum = 0;
        int count = 0;
        for (int dy = -1; dy <= 1; ++dy) {
          for (int dx = -1; dx <= 1; ++dx) {
            const int xx = x + dx, yy = y + dy;
            if (xx < 0 || yy < 0 || xx >= fine.width || yy >= fine.height) continue;
            const float z = out[static_cast<size_t>(yy) * fine.width + xx];
            if (z > 0) sum += z, ++count;
          }
        }
        if (count > 0) next[i] = static_cast<float>(sum / count);
      }
    }
    out.swap(next);
  }
  return out;
}

// Each depth replaced by the median of the known depths about it (radius r; 0: none): a coarse level's outliers
// would otherwise steer the finer levels' narrow sweeps, which cannot reach past them.
DepthMap MedianDepth(const DepthMap& in, int r) {
  if (r <= 0) return in;
  DepthMap out = in;
  std::vector<float> v;
  for (int y = 0; y < in.height; ++y) {
    for (int x = 0; x < in.width; ++x) {
      const size_t i = static_cast<size_t>(y) * in.width + x;
      if (in.depth[i] <= 0) continue;
      v.clear();
      for (int yy = std::max(0, y - r); yy <= std::min(in.height - 1, y + r); ++yy) {
        for (int xx = std::max(0, x - r); xx <= std::min(in.width - 1, x + r); ++xx) {
          const float z = in.depth[static_cast<size_t>(yy) * in.width + xx];
          if (z > 0) v.push_back(z);
        }
      }
      std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
      out.depth[i] = v[v.size() / 2];
    }
  }
  return out;
}

// One level's sweep of view `ref`.
DepthMap SweepLevel(const Level& rl, const RefStats& rs, const std::vector<const Level*>& nls,
                    const std::vector<PairWarp>& warps, const Hypotheses& h, const MvsOptions& o, double min_score,
                    bool keep_boundary) {
  std::vector<cv::Mat> cost(h.count);
  std::vector<cv::Mat> scores(nls.size());
  for (int k = 0; k < h.count; ++k) {
    for (size_t n = 0; n < nls.size(); ++n) scores[n] = ScoreAgainst(rl, rs, *nls[n], warps[n], h, k, o.window);
    cost[k] = BestOf(scores, o.best_of);
  }
  DepthMap out;
  PickBest(cost, h, min_score, keep_boundary, &out);
  return out;
}

}  // namespace

std::vector<std::vector<int>> ChooseNeighbours(const std::vector<MvsView>& views, const MvsOptions& options) {
  std::vector<std::vector<int>> out(views.size());
  for (size_t r = 0; r < views.size(); ++r) {
    const Eigen::Vector3d axis = views[r].rotation.row(2).transpose();
    std::vector<std::pair<double, int>> near;
    for (size_t n = 0; n < views.size(); ++n) {
      if (n == r) continue;
      const double angle = std::acos(std::clamp(axis.dot(views[n].rotation.row(2).transpose()), -1.0, 1.0)) * 180 / kPi;
      if (angle >= options.min_angle_deg && angle <= options.max_angle_deg)
        near.emplace_back(angle, static_cast<int>(n));
    }
    std::sort(near.begin(), near.end());
    for (size_t i = 0; i < near.size() && static_cast<int>(i) < options.neighbours; ++i) {
      out[r].push_back(near[i].second);
    }
  }
  return out;
}

DepthMap SweepDepth(const std::vector<MvsView>& views, int ref, const std::vector<int>& neighbours,
                    const MvsOptions& options, MvsViewMetrics* metrics) {
  const MvsView& rv = views[ref];
  int levels = 1;
  while ((rv.width >> (levels - 1)) > options.coarse_width && (rv.height >> levels) >= 16) ++levels;
  const std::vector<Level> rp = BuildPyramid(rv, levels);
  std::vector<std::vector<Level>> np;
  for (int n : neighbours) np.push_back(BuildPyramid(views[n], levels));
  const float min_signal = static_cast<float>(options.min_signal) * static_cast<float>(Quantile(rv.grey, 99, 100));

  DepthMap depth;
  for (int l = levels - 1; l >= 0; --l) {
    const Level& rl = rp[l];
    const RefStats rs = MakeRefStats(rl, min_signal, options.window);
    std::vector<const Level*> nls;
    std::vector<PairWarp> warps;
    for (size_t n = 0; n < neighbours.size(); ++n) {
      nls.push_back(&np[n][l]);
      warps.push_back(MakeWarp(rv, rl, views[neighbours[n]], np[n][l]));
    }
    const Hypotheses h =
        l == levels - 1 ? VolumeSweep(rv, rl, warps, options)
                        : RefineSweep(rl, Upsample(MedianDepth(depth, options.prior_median_radius), rl, rs.foreground),
                                      warps, options.refine_steps);
    // Coarser levels keep weaker matches: the finer levels look again.
    const bool finest = l == 0;
    depth = SweepLevel(rl, rs, nls, warps, h, options, finest ? options.min_score : 0.5 * options.min_score, !finest);
    if (options.keep_coarser && l < levels - 1) {
      // Where this level finds nothing (too little texture in its window, or no score high enough), the coarser
      // level's depth stands: its windows cover more of the surface. The agreement across views judges it.
      for (size_t i = 0; i < depth.depth.size(); ++i) {
        if (depth.depth[i] <= 0 && h.step[i] > 0) depth.depth[i] = h.z0[i];
      }
    }
    if (finest && metrics != nullptr) {
      metrics->foreground = cv::countNonZero(rs.foreground);
      metrics->matched = std::count_if(depth.depth.begin(), depth.depth.end(), [](float z) { return z > 0; });
    }
  }
  return depth;
}

int64_t KeepConsistent(const std::vector<MvsView>& views, const std::vector<DepthMap>& depths, int ref,
                       const std::vector<int>& neighbours, const MvsOptions& options, DepthMap* out) {
  const MvsView& r = views[ref];
  const DepthMap& in = depths[ref];
  *out = in;
  const Eigen::Matrix3d to_ray =
      r.rotation.transpose() * (Eigen::Matrix3d() << r.fx, 0, r.cx, 0, r.fy, r.cy, 0, 0, 1).finished().inverse();
  // Per neighbour, the sine of the pair's angle: how far a pixel of matching moves the depth is a pixel's footprint
  // over it.
  std::vector<double> sines;
  for (int n : neighbours) sines.push_back(std::max(0.1, r.rotation.row(2).cross(views[n].rotation.row(2)).norm()));
  int64_t kept = 0;
  for (int y = 0; y < in.height; ++y) {
    for (int x = 0; x < in.width; ++x) {
      const size_t i = static_cast<size_t>(y) * in.width + x;
      if (in.depth[i] <= 0) continue;
      const Eigen::Vector3d p = r.position + in.depth[i] * (to_ray * Eigen::Vector3d(x, y, 1));
      int agree = 0;
      for (size_t k = 0; k < neighbours.size(); ++k) {
        const int n = neighbours[k];
        const MvsView& v = views[n];
        const Eigen::Vector3d c = v.rotation * (p - v.position);
        if (c.z() <= 0) continue;
        const int u = static_cast<int>(std::lround(v.fx * c.x() / c.z() + v.cx));
        const int w = static_cast<int>(std::lround(v.fy * c.y() / c.z() + v.cy));
        if (u < 0 || w < 0 || u >= v.width || w >= v.height) continue;
        const float zn = depths[n].depth[static_cast<size_t>(w) * v.width + u];
        if (zn <= 0) continue;
        const double tolerance = options.consistency_px * c.z() / v.fx / sines[k];
        if (std::abs(zn - c.z()) <= tolerance) ++agree;
      }
      if (agree >= options.min_consistent) {
        ++kept;
      } else {
        out->depth[i] = 0;
        out->score[i] = -1;
      }
    }
  }
  return kept;
}

TriangleMesh TrimToHead(const TriangleMesh& mesh, const Eigen::Vector3d& centre, double radius_mm) {
  const int nv = static_cast<int>(mesh.positions.size());
  std::vector<int> parent(nv);
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int a) {
    while (parent[a] != a) a = parent[a] = parent[parent[a]];
    return a;
  };
  const Eigen::Vector3f c = centre.cast<float>();
  const float r2 = static_cast<float>(radius_mm * radius_mm);
  auto inside = [&](int v) { return (mesh.positions[v] - c).squaredNorm() <= r2; };
  std::vector<char> keep_tri(mesh.triangles.size(), 0);
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    const auto& tri = mesh.triangles[t];
    if (!inside(tri[0]) || !inside(tri[1]) || !inside(tri[2])) continue;
    keep_tri[t] = 1;
    parent[find(tri[1])] = find(tri[0]);
    parent[find(tri[2])] = find(tri[0]);
  }
  std::vector<int64_t> size(nv, 0);
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    if (keep_tri[t]) ++size[find(mesh.triangles[t][0])];
  }
  const int biggest = static_cast<int>(std::max_element(size.begin(), size.end()) - size.begin());
  TriangleMesh out;
  std::vector<int32_t> index(nv, -1);
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    if (!keep_tri[t] || find(mesh.triangles[t][0]) != biggest) continue;
    std::array<int32_t, 3> tri;
    for (int k = 0; k < 3; ++k) {
      int32_t& j = index[mesh.triangles[t][k]];
      if (j < 0) {
        j = static_cast<int32_t>(out.positions.size());
        out.positions.push_back(mesh.positions[mesh.triangles[t][k]]);
      }
      tri[k] = j;
    }
    out.triangles.push_back(tri);
  }
  return out;
}

void SmoothMesh(int iterations, TriangleMesh* mesh) {
  const size_t n = mesh->positions.size();
  std::vector<std::vector<int32_t>> ring(n);
  for (const auto& t : mesh->triangles) {
    for (int k = 0; k < 3; ++k) {
      ring[t[k]].push_back(t[(k + 1) % 3]);
      ring[t[k]].push_back(t[(k + 2) % 3]);
    }
  }
  for (auto& r : ring) {
    std::sort(r.begin(), r.end());
    r.erase(std::unique(r.begin(), r.end()), r.end());
  }
  std::vector<Eigen::Vector3f> next(n);
  auto step = [&](float factor) {
    for (size_t v = 0; v < n; ++v) {
      if (ring[v].empty()) {
        next[v] = mesh->positions[v];
        continue;
      }
      Eigen::Vector3f mean = Eigen::Vector3f::Zero();
      for (int32_t u : ring[v]) mean += mesh->positions[u];
      mean /= static_cast<float>(ring[v].size());
      next[v] = mesh->positions[v] + factor * (mean - mesh->positions[v]);
    }
    mesh->positions.swap(next);
  };
  // Taubin's lambda | mu: a shrinking step and an inflating one, so the surface keeps its size.
  for (int i = 0; i < iterations; ++i) {
    step(0.5f);
    step(-0.53f);
  }
}

}  // namespace stage::processing
