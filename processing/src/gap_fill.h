// Growing an image's set pixels into the empty ones about them: the geometry's fill in photometric stereo, the
// dilation of UV maps past their seams.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace stage::processing {

enum class GapGrowth {
  kMean,    // an empty pixel takes the mean of its set 8-neighbours
  kLinear,  // it continues them: from a set neighbour at offset d whose own at 2d is set too, 2 v(d) - v(2d); from
            // one without, v(d); the mean over the directions (a surface grows along its slope, not flat)
};

// The empty pixels (NaN in their first channel) of a w x h image of `channels` interleaved floats, within `passes`
// pixels of set ones, grow one ring a pass. Returns the rings grown. Each pass visits only the ring it grows (an empty
// pixel next to one set in the pass before: any other empty pixel with a set neighbour would have grown earlier), so a
// pass costs its ring, not the image.
inline int GrowIntoGaps(int w, int h, int channels, int passes, GapGrowth growth, std::vector<float>* values) {
  std::vector<float>& v = *values;
  const auto c = static_cast<size_t>(channels);
  auto set = [&](int x, int y) {
    return v[(static_cast<size_t>(y) * w + x) * c] == v[(static_cast<size_t>(y) * w + x) * c];
  };
  auto at = [&](int x, int y) -> const float* {
    if (x < 0 || y < 0 || x >= w || y >= h) return nullptr;
    const float* p = &v[(static_cast<size_t>(y) * w + x) * c];
    return p[0] == p[0] ? p : nullptr;
  };
  // The first ring: empty pixels with a set 8-neighbour, in raster order.
  std::vector<size_t> ring;
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      if (set(x, y)) continue;
      bool near = false;
      for (int dy = -1; dy <= 1 && !near; ++dy) {
        for (int dx = -1; dx <= 1 && !near; ++dx) near = (dx != 0 || dy != 0) && at(x + dx, y + dy) != nullptr;
      }
      if (near) ring.push_back(static_cast<size_t>(y) * w + x);
    }
  }
  std::vector<uint8_t> queued(static_cast<size_t>(w) * h, 0);
  std::vector<float> grown;
  std::vector<float> sum(c);
  for (int pass = 0; pass < passes; ++pass) {
    if (ring.empty()) return pass;
    grown.assign(ring.size() * c, 0.0f);
    for (size_t r = 0; r < ring.size(); ++r) {
      const int x = static_cast<int>(ring[r] % w), y = static_cast<int>(ring[r] / w);
      std::fill(sum.begin(), sum.end(), 0.0f);
      int n = 0;
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const float* d1 = (dx == 0 && dy == 0) ? nullptr : at(x + dx, y + dy);
          if (d1 == nullptr) continue;
          const float* d2 = growth == GapGrowth::kLinear ? at(x + 2 * dx, y + 2 * dy) : nullptr;
          for (size_t k = 0; k < c; ++k) sum[k] += d2 != nullptr ? 2 * d1[k] - d2[k] : d1[k];
          ++n;
        }
      }
      for (size_t k = 0; k < c; ++k) grown[r * c + k] = sum[k] / static_cast<float>(n);
    }
    for (size_t r = 0; r < ring.size(); ++r) std::copy_n(&grown[r * c], c, &v[ring[r] * c]);
    // The next ring: the empty neighbours of this one, in raster order (as the full scan would meet them).
    std::vector<size_t> next;
    for (size_t i : ring) {
      const int x = static_cast<int>(i % w), y = static_cast<int>(i / w);
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const int nx = x + dx, ny = y + dy;
          if (nx < 0 || ny < 0 || nx >= w || ny >= h || set(nx, ny)) continue;
          const size_t j = static_cast<size_t>(ny) * w + nx;
          if (queued[j]) continue;
          queued[j] = 1;
          next.push_back(j);
        }
      }
    }
    for (size_t j : next) queued[j] = 0;
    std::sort(next.begin(), next.end());
    ring = std::move(next);
  }
  return passes;
}

}  // namespace stage::processing
