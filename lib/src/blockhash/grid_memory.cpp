// The grid's host arrays (grid.hpp's NoInitAllocator): large ones on transparent huge pages, and a
// bounded cache of the large blocks freed, handed to the next allocation that fits (issue 39).
//
// Why a cache: freed to glibc, a block of 4 MiB or more is unmapped (or trimmed), and the next
// one is mapped afresh. On a VM whose balloon reports free pages to the host (Firecracker's
// virtio_balloon here), the first touch of a page the process gave back is slow: 80 MB touched
// for the first time took 127 ms, touched again 8 ms (bench/results/e2e/fresh_pages.txt). A
// rebuild across the retune band (a 25 % insert on 1M points) wrote its new arrays on such pages:
// 30 ms against a fresh build's 17-19 ms, 10-12 ms with glibc told to keep its memory. The
// cache keeps those pages in the process, as PyTorch's caching host allocator and CUB's caching
// allocator do, up to a bound (BHCL_HOST_CACHE_MB; release_host_cache gives them back).
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <mutex>
#include <new>
#include <unordered_map>
#include <vector>

#include "blockhash/grid.hpp"
#include "blockhash_cl/grid_index.hpp"

namespace bhcl::blockhash {
namespace {

constexpr std::size_t kHuge = std::size_t(2) << 20;  // the huge page, and the large blocks' alignment
constexpr std::size_t kLarge = 2 * kHuge;             // from here on: huge pages and the cache

std::size_t rounded_up(std::size_t bytes) { return (bytes + kHuge - 1) / kHuge * kHuge; }

}  // namespace

std::size_t host_cache_limit_from(const char* env) {
  if (env && *env) {
    char* end = nullptr;
    const unsigned long long mb = std::strtoull(env, &end, 10);
    if (end != env && *end == 0 && env[0] != '-' && mb <= (std::size_t(-1) >> 20)) return std::size_t(mb) << 20;
  }
  std::size_t limit = std::size_t(512) << 20;
  const long pages = ::sysconf(_SC_PHYS_PAGES), page = ::sysconf(_SC_PAGE_SIZE);
  if (pages > 0 && page > 0) limit = std::min(limit, std::size_t(pages) / 8 * std::size_t(page));
  return limit;
}

namespace {

struct Cache {
  struct Block {
    void* p;
    std::size_t bytes;  // the block's own size (a multiple of kHuge)
  };
  std::mutex mutex;
  std::vector<Block> kept;  // oldest first
  std::size_t held = 0;     // the bytes in `kept`
  std::size_t limit = host_cache_limit_from(std::getenv("BHCL_HOST_CACHE_MB"));  // read once
  // Blocks handed out larger than their request's rounded size: their own size, which the
  // deallocation (told the request's) must free or cache.
  std::unordered_map<void*, std::size_t> larger;

  // Frees the oldest blocks until `held` is at most `bound`; the bytes freed. Under the mutex.
  std::size_t trim_to(std::size_t bound) {
    std::size_t k = 0, freed = 0;
    while (held > bound && k < kept.size()) {
      held -= kept[k].bytes, freed += kept[k].bytes;
      std::free(kept[k++].p);
    }
    kept.erase(kept.begin(), kept.begin() + std::ptrdiff_t(k));
    return freed;
  }
};

// Never destroyed, so that arrays freed by static destructors after main still find it; the
// blocks it holds stay reachable through it (LeakSanitizer does not report them at exit).
Cache& cache() {
  static Cache* c = new Cache;
  return *c;
}

// The cached block that fits a request of `want` bytes (a multiple of kHuge): the smallest of
// those at least `want` and at most kFitNum / kFitDen of it (a small array does not hold a large
// block), the newest of equal ones. nullptr when none.
constexpr std::size_t kFitNum = 5, kFitDen = 4;
void* take(std::size_t want) {
  Cache& c = cache();
  std::lock_guard<std::mutex> lock(c.mutex);
  std::size_t best = c.kept.size();
  for (std::size_t i = c.kept.size(); i-- > 0;) {
    const std::size_t b = c.kept[i].bytes;
    if (b >= want && b * kFitDen <= want * kFitNum && (best == c.kept.size() || b < c.kept[best].bytes)) best = i;
  }
  if (best == c.kept.size()) return nullptr;
  const Cache::Block blk = c.kept[best];
  c.kept.erase(c.kept.begin() + std::ptrdiff_t(best));
  c.held -= blk.bytes;
  if (blk.bytes != want) try {
      c.larger.emplace(blk.p, blk.bytes);
    } catch (...) {  // no memory for the entry: the block goes back, the request allocates
      std::free(blk.p);
      return nullptr;
    }
  return blk.p;
}

}  // namespace

void* grid_allocate(std::size_t bytes) {
  if (bytes >= kLarge) {
    const std::size_t want = rounded_up(bytes);
    void* p = take(want);
    if (!p) p = std::aligned_alloc(kHuge, want);
    if (!p && release_host_cache()) p = std::aligned_alloc(kHuge, want);  // the cache's memory first
    if (!p) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
    // Advice only: without it the pages are 4 KiB. Again for a cached block, whose previous
    // owner may have advised small pages for its room (grid_build.cpp's resize_discarding).
    ::madvise(p, want, MADV_HUGEPAGE);
#endif
    return p;
  }
  if (void* p = std::malloc(bytes ? bytes : 1)) return p;
  throw std::bad_alloc();
}

void grid_deallocate(void* p, std::size_t bytes) noexcept {
  if (!p) return;
  if (bytes < kLarge) {
    std::free(p);
    return;
  }
  Cache& c = cache();
  std::lock_guard<std::mutex> lock(c.mutex);
  std::size_t size = rounded_up(bytes);
  if (!c.larger.empty())
    if (auto it = c.larger.find(p); it != c.larger.end()) size = it->second, c.larger.erase(it);
  if (size > c.limit) {
    std::free(p);
    return;
  }
  try {
    c.kept.push_back({p, size});
  } catch (...) {  // no memory for the list's entry: the block goes back instead
    std::free(p);
    return;
  }
  c.held += size;
  c.trim_to(c.limit);
}

std::size_t host_cache_set_limit(std::size_t bytes) {
  Cache& c = cache();
  std::lock_guard<std::mutex> lock(c.mutex);
  const std::size_t old = c.limit;
  c.limit = bytes;
  c.trim_to(bytes);
  return old;
}

HostCacheState host_cache_state() {
  Cache& c = cache();
  std::lock_guard<std::mutex> lock(c.mutex);
  return {c.held, c.kept.size(), c.limit};
}

}  // namespace bhcl::blockhash

namespace bhcl {

std::size_t release_host_cache() {
  blockhash::Cache& c = blockhash::cache();
  std::lock_guard<std::mutex> lock(c.mutex);
  return c.trim_to(0);
}

}  // namespace bhcl
