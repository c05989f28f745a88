// Growing an image's set pixels into the empty ones about them: the geometry's fill in photometric stereo, the
// dilation of UV maps past their seams.
#pragma once

#include <algorithm>
#include <cstddef>
#include <vector>

namespace stage::processing {

enum class GapGrowth {
  kMean,    // an empty pixel takes the mean of its set 8-neighbours
  kLinear,  // it continues them: from a set neighbour at offset d whose own at 2d is set too, 2 v(d) - v(2d); from
            // one without, v(d); the mean over the directions (a surface grows along its slope, not flat)
};

// The empty pixels (NaN in their first channel) of a w x h image of `channels` interleaved floats, within `passes`
// pixels of set ones, grow one ring a pass. Returns the rings grown.
inline int GrowIntoGaps(int w, int h, int channels, int passes, GapGrowth growth, std::vector<float>* values) {
  std::vector<float>& v = *values;
  std::vector<float> next = v;
  const auto c = static_cast<size_t>(channels);
  std::vector<float> sum(c);
  auto at = [&](int x, int y) -> const float* {
    if (x < 0 || y < 0 || x >= w || y >= h) return nullptr;
    const float* p = &v[(static_cast<size_t>(y) * w + x) * c];
    return p[0] == p[0] ? p : nullptr;
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
            const float* d1 = (dx == 0 && dy == 0) ? nullptr : at(x + dx, y + dy);
            if (d1 == nullptr) continue;
            const float* d2 = growth == GapGrowth::kLinear ? at(x + 2 * dx, y + 2 * dy) : nullptr;
            for (size_t k = 0; k < c; ++k) sum[k] += d2 != nullptr ? 2 * d1[k] - d2[k] : d1[k];
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
