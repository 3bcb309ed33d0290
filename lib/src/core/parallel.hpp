// One way to split host work over threads (builds and host references): contiguous ranges, one
// per thread, joined before return. Exceptions from a worker are rethrown in the caller.
#pragma once

#include <algorithm>
#include <cstddef>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace bhcl::detail {

inline unsigned default_threads() { return std::max(1u, std::thread::hardware_concurrency()); }

// Calls fn(begin, end) on [0, n) cut into `threads` contiguous ranges (0: all hardware threads);
// small n runs inline.
template <typename Fn>
void parallel_for(std::size_t n, Fn&& fn, unsigned threads = 0, std::size_t min_per_thread = 4096) {
  if (threads == 0) threads = default_threads();
  std::size_t t = std::min<std::size_t>(threads, std::max<std::size_t>(1, n / std::max<std::size_t>(1, min_per_thread)));
  if (t <= 1) {
    if (n) fn(std::size_t(0), n);
    return;
  }
  std::vector<std::thread> pool;
  std::exception_ptr error;
  std::mutex m;
  const std::size_t per = (n + t - 1) / t;
  for (std::size_t i = 0; i < t; ++i) {
    std::size_t b = i * per, e = std::min(n, b + per);
    if (b >= e) break;
    pool.emplace_back([&, b, e] {
      try {
        fn(b, e);
      } catch (...) {
        std::lock_guard<std::mutex> lock(m);
        if (!error) error = std::current_exception();
      }
    });
  }
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

}  // namespace bhcl::detail
