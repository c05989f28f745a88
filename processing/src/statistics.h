// Small statistics shared by the processing stages' metrics and evaluations.
#pragma once

#include <algorithm>
#include <cstddef>
#include <vector>

namespace stage::processing {

// The upper median (the element at size / 2 once sorted); 0 for none.
template <typename T>
double Median(std::vector<T> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
  return static_cast<double>(v[v.size() / 2]);
}

}  // namespace stage::processing
