// Work spread over threads: bands of rows handed out in turn.
#pragma once

#include <algorithm>
#include <atomic>
#include <thread>
#include <vector>

namespace stage::processing::internal {

// Runs body(y0, y1) over bands of rows on `threads` threads (0: one per core).
template <typename F>
void ParallelRows(int height, int threads, F body) {
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  // Small bands handed out in turn, so that a band of background does not leave a thread idle.
  const int band = std::max(1, std::min(16, height / (4 * threads)));
  std::atomic<int> next{0};
  auto worker = [&] {
    for (int y0; (y0 = next.fetch_add(band)) < height;) body(y0, std::min(height, y0 + band));
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(worker);
  worker();
  for (auto& th : pool) th.join();
}

// Runs body(i) for i in [0, count) on `threads` threads (0: one per core), items handed out in turn.
template <typename F>
void ParallelItems(int count, int threads, F body) {
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  std::atomic<int> next{0};
  auto worker = [&] {
    for (int i; (i = next.fetch_add(1)) < count;) body(i);
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < std::min(threads, count); ++t) pool.emplace_back(worker);
  worker();
  for (auto& th : pool) th.join();
}

}  // namespace stage::processing::internal
