// Growing an image's set pixels into the empty ones about them: the geometry's fill in photometric stereo, the
// dilation of UV maps past their seams.
#pragma once

#include <algorithm>
#include <cstddef>
#include <vector>

namespace stage::processing {

// The empty pixels (NaN in their first channel) of a w x h image of `channels` interleaved floats, within `passes`
// pixels of set ones, take one ring a pass the mean of their set 8-neighbours. Returns the rings grown.
inline int SpreadIntoGaps(int w, int h, int channels, int passes, std::vector<float>* values) {
  std::vector<float>& v = *values;
  std::vector<float> next = v;
  const auto c = static_cast<size_t>(channels);
  std::vector<float> sum(c);
  for (int pass = 0; pass < passes; ++pass) {
    bool grew = false;
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = (static_cast<size_t>(y) * w + x) * c;
        if (v[i] == v[i]) continue;
        std::fill(sum.begin(), sum.end(), 0.0f);
        int n = 0;
        for (int yy = std::max(y - 1, 0); yy <= std::min(y + 1, h - 1); ++yy) {
          for (int xx = std::max(x - 1, 0); xx <= std::min(x + 1, w - 1); ++xx) {
            const float* d = &v[(static_cast<size_t>(yy) * w + xx) * c];
            if (d[0] != d[0]) continue;
            for (size_t k = 0; k < c; ++k) sum[k] += d[k];
            ++n;
          }
        }
        if (n == 0) continue;
        for (size_t k = 0; k < c; ++k) next[i + k] = sum[k] / static_cast<float>(n);
        grew = true;
      }
    }
    if (!grew) return pass;
    v = next;
  }
  return passes;
}

// As SpreadIntoGaps, but each empty pixel continues its set neighbours linearly: from a set neighbour at offset d whose
// own neighbour at 2d is set too, 2 v(d) - v(2d); from one without, v(d); the mean over the 8 directions. A surface
// (a UV geometry map) grows past its edge along its slope instead of flattening there.
inline int GrowLinearlyIntoGaps(int w, int h, int channels, int passes, std::vector<float>* values) {
  std::vector<float>& v = *values;
  std::vector<float> next = v;
  const auto c = static_cast<size_t>(channels);
  std::vector<float> sum(c);
  auto set = [&](int x, int y) {
    return x >= 0 && y >= 0 && x < w && y < h &&
           v[(static_cast<size_t>(y) * w + x) * c] == v[(static_cast<size_t>(y) * w + x) * c];
  };
  for (int pass = 0; pass < passes; ++pass) {
    bool grew = false;
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const size_t i = (static_cast<size_t>(y) * w + x) * c;
        if (v[i] == v[i]) continue;
        std::fill(sum.begin(), sum.end(), 0.0f);
        int n = 0;
        for (int dy = -1; dy <= 1; ++dy) {
          for (int dx = -1; dx <= 1; ++dx) {
            if ((dx == 0 && dy == 0) || !set(x + dx, y + dy)) continue;
            const float* d1 = &v[(static_cast<size_t>(y + dy) * w + x + dx) * c];
            const bool far = set(x + 2 * dx, y + 2 * dy);
            const float* d2 = far ? &v[(static_cast<size_t>(y + 2 * dy) * w + x + 2 * dx) * c] : d1;
            for (size_t k = 0; k < c; ++k) sum[k] += 2 * d1[k] - d2[k];
            ++n;
          }
        }
        if (n == 0) continue;
        for (size_t k = 0; k < c; ++k) next[i + k] = sum[k] / static_cast<float>(n);
        grew = true;
      }
    }
    if (!grew) return pass;
    v = next;
  }
  return passes;
}

}  // namespace stage::processing
