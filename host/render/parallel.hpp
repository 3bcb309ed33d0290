// The renderer's parallel loops: the library's (blockhash_cl/parallel.hpp), chunked so that work is
// cut into chunks that depend only on the problem size (per-chunk outputs concatenated in chunk
// order do not depend on the thread count). Exceptions are rethrown on the calling thread.
#pragma once

#include <algorithm>
#include <cstddef>
#include <thread>

#include "blockhash_cl/parallel.hpp"

namespace bhcl::render {

// 0: the CPUs this process may use (its affinity mask), as the library's loops resolve it, not
// hardware_concurrency() (every CPU of the machine, pinned or not).
inline int resolve_threads(int threads) {
  return threads > 0 ? threads : static_cast<int>(detail::default_threads());
}

// fn(chunk_index, begin, end) for chunks [c*chunk, min(n, (c+1)*chunk)).
template <typename Fn>
void parallel_chunks(std::size_t n, std::size_t chunk, int threads, Fn&& fn) {
  detail::parallel_chunks(n, chunk, static_cast<unsigned>(resolve_threads(threads)), fn);
}

}  // namespace bhcl::render
