#include "gap_fill.h"

#include <cmath>
#include <random>

#include "gtest/gtest.h"

namespace stage::processing {
namespace {

// The definition, one full scan of the image a pass: every empty pixel with a set 8-neighbour takes their mean (or
// their continuation) from the image as the pass found it.
int ReferenceGrow(int w, int h, int c, int passes, GapGrowth growth, std::vector<float>* values) {
  std::vector<float>& v = *values;
  auto at = [&](int x, int y) -> const float* {
    if (x < 0 || y < 0 || x >= w || y >= h) return nullptr;
    const float* p = &v[(static_cast<size_t>(y) * w + x) * c];
    return std::isnan(p[0]) ? nullptr : p;
  };
  for (int pass = 0; pass < passes; ++pass) {
    std::vector<float> next = v;
    bool grew = false;
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        if (at(x, y) != nullptr) continue;
        std::vector<float> sum(static_cast<size_t>(c), 0.0f);
        int n = 0;
        for (int dy = -1; dy <= 1; ++dy) {
          for (int dx = -1; dx <= 1; ++dx) {
            const float* d1 = (dx == 0 && dy == 0) ? nullptr : at(x + dx, y + dy);
            if (d1 == nullptr) continue;
            const float* d2 = growth == GapGrowth::kLinear ? at(x + 2 * dx, y + 2 * dy) : nullptr;
            for (int k = 0; k < c; ++k) sum[k] += d2 != nullptr ? 2 * d1[k] - d2[k] : d1[k];
            ++n;
          }
        }
        if (n == 0) continue;
        for (int k = 0; k < c; ++k) next[(static_cast<size_t>(y) * w + x) * c + k] = sum[k] / static_cast<float>(n);
        grew = true;
      }
    }
    if (!grew) return pass;
    v = next;
  }
  return passes;
}

TEST(GapFillTest, GrowingRingByRingIsTheFullScanBitForBit) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> value(-1, 1), hole(0, 1);
  for (GapGrowth growth : {GapGrowth::kMean, GapGrowth::kLinear}) {
    for (int passes : {1, 3, 50}) {
      const int w = 61, h = 37, c = 3;
      std::vector<float> image(static_cast<size_t>(w) * h * c);
      for (int y = 0; y < h; ++y) {
        for (int x = 0; x < w; ++x) {
          // Set pixels in a few blobs and scattered dots; the rest empty.
          const bool set = std::hypot(x - 15, y - 12) < 8 || std::hypot(x - 45, y - 25) < 5 || hole(rng) < 0.02f;
          for (int k = 0; k < c; ++k) image[(static_cast<size_t>(y) * w + x) * c + k] = set ? value(rng) : NAN;
        }
      }
      std::vector<float> fast = image, reference = image;
      const int rings = GrowIntoGaps(w, h, c, passes, growth, &fast);
      EXPECT_EQ(rings, ReferenceGrow(w, h, c, passes, growth, &reference));
      for (size_t i = 0; i < fast.size(); ++i) {
        ASSERT_TRUE((std::isnan(fast[i]) && std::isnan(reference[i])) || fast[i] == reference[i])
            << "value " << i << " after " << passes << " passes: " << fast[i] << " vs " << reference[i];
      }
    }
  }
}

}  // namespace
}  // namespace stage::processing
