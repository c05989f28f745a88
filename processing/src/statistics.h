// Small statistics shared by the processing stages' metrics and evaluations.
#pragma once

#include <algorithm>
#include <cstddef>
#include <utility>
#include <vector>

namespace stage::processing {

// The element at size * num / den once sorted (num < den): Quantile(v, 99, 100) is the 99th percentile; 0 for none.
template <typename T>
double Quantile(std::vector<T> v, size_t num, size_t den) {
  if (v.empty()) return 0;
  const size_t k = v.size() * num / den;
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return static_cast<double>(v[k]);
}

// The upper median (the element at size / 2 once sorted); 0 for none.
template <typename T>
double Median(std::vector<T> v) {
  return Quantile(std::move(v), 1, 2);
}

}  // namespace stage::processing
