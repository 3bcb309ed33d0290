// Fixed-chunk parallel loop on std::threads. Work is cut into chunks that depend only on the
// problem size, so per-chunk outputs concatenated in chunk order do not depend on thread count.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace bhcl::render {

inline int resolve_threads(int threads) {
  return threads > 0 ? threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
}

// fn(chunk_index, begin, end) for chunks [c*chunk, min(n, (c+1)*chunk)). Exceptions are re-thrown
// on the calling thread (the first one).
template <typename Fn>
void parallel_chunks(std::size_t n, std::size_t chunk, int threads, Fn&& fn) {
  if (n == 0) return;
  const std::size_t chunks = (n + chunk - 1) / chunk;
  std::atomic<std::size_t> next{0};
  std::exception_ptr error;
  std::mutex error_mutex;
  auto work = [&] {
    for (;;) {
      std::size_t c = next.fetch_add(1);
      if (c >= chunks) return;
      try {
        fn(c, c * chunk, std::min(n, (c + 1) * chunk));
      } catch (...) {
        std::lock_guard<std::mutex> lock(error_mutex);
        if (!error) error = std::current_exception();
        next = chunks;
      }
    }
  };
  int t = std::min<int>(resolve_threads(threads), static_cast<int>(chunks));
  std::vector<std::thread> pool;
  for (int i = 1; i < t; ++i) pool.emplace_back(work);
  work();
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

}  // namespace bhcl::render
