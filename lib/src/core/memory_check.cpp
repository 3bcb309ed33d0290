// check_result_memory (blockhash_cl/knn.hpp): a result too large for the memory this process can
// still allocate is refused before the search, naming what bounds it.
#include "blockhash_cl/knn.hpp"

#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>

#include <sys/resource.h>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/grid_index.hpp"  // release_host_cache

namespace bhcl {
namespace {

// "7.2 GB": decimal gigabytes, one decimal.
std::string gigabytes(double bytes) {
  std::ostringstream os;
  os.setf(std::ios::fixed);
  os.precision(1);
  os << bytes / 1e9 << " GB";
  return os.str();
}

// A number from a /proc or /sys file: the value after `key` (the whole file when key is empty),
// times `unit`; 0 when absent or unlimited ("max").
std::uint64_t number_in_file(const char* path, const std::string& key, std::uint64_t unit) {
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    if (!key.empty() && line.compare(0, key.size(), key) != 0) continue;
    const char* p = line.c_str() + key.size();
    char* end = nullptr;
    const unsigned long long v = std::strtoull(p, &end, 10);
    return end == p ? 0 : static_cast<std::uint64_t>(v) * unit;
  }
  return 0;
}

// The memory this process can still allocate, and what bounds it: the address-space and data
// limits (less what is mapped), the cgroup's memory.max (less what it uses), and the machine's
// available memory plus free swap. UINT64_MAX when nothing is known.
std::uint64_t allocatable_bytes(std::string* bound) {
  std::uint64_t best = std::numeric_limits<std::uint64_t>::max();
  auto consider = [&](std::uint64_t v, const char* what) {
    if (v < best) {
      best = v;
      *bound = what;
    }
  };
  rlimit rl{};
  if (getrlimit(RLIMIT_AS, &rl) == 0 && rl.rlim_cur != RLIM_INFINITY) {
    const std::uint64_t used = number_in_file("/proc/self/status", "VmSize:", 1024);
    consider(rl.rlim_cur > used ? rl.rlim_cur - used : 0, "the address-space limit (ulimit -v)");
  }
  if (getrlimit(RLIMIT_DATA, &rl) == 0 && rl.rlim_cur != RLIM_INFINITY) {
    const std::uint64_t used = number_in_file("/proc/self/status", "VmData:", 1024);
    consider(rl.rlim_cur > used ? rl.rlim_cur - used : 0, "the data-size limit (ulimit -d)");
  }
  if (const std::uint64_t max = number_in_file("/sys/fs/cgroup/memory.max", "", 1)) {
    const std::uint64_t used = number_in_file("/sys/fs/cgroup/memory.current", "", 1);
    consider(max > used ? max - used : 0, "the cgroup's memory.max");
  }
  const std::uint64_t avail = number_in_file("/proc/meminfo", "MemAvailable:", 1024);
  if (avail) consider(avail + number_in_file("/proc/meminfo", "SwapFree:", 1024), "the machine's available memory");
  return best;
}

// allocatable_bytes, and where `need` is more than that, again after the grid's host block cache
// has given its blocks back (they count as used here, and only grid arrays can reuse them).
std::uint64_t allocatable_for(double need, std::string* bound) {
  const std::uint64_t can = allocatable_bytes(bound);
  if (need <= double(can) || release_host_cache() == 0) return can;
  return allocatable_bytes(bound);
}

}  // namespace

void check_result_memory(std::size_t n, int k, bool examined, int copies, const std::string& method) {
  const double bytes = (double(n) * k * 8.0 + double(n) * (examined ? 8.0 : 4.0)) * copies + (copies > 1 ? 20.0 * n : 0.0);
  if (bytes < double(std::size_t(64) << 20)) return;  // small results: not worth the /proc reads
  std::string bound;
  const std::uint64_t can = allocatable_for(bytes, &bound);
  if (bytes > double(std::numeric_limits<std::size_t>::max() / 2) || bytes > double(can)) {
    std::ostringstream os;
    os << method << " query: the result needs " << gigabytes(bytes) << " (n = " << n << " queries x k = " << k
       << ": ids and squared distances" << (copies > 1 ? ", and the Hilbert-ordered copy" : "") << ")";
    if (can != std::numeric_limits<std::uint64_t>::max()) os << ", more than the " << gigabytes(double(can)) << " that " << bound << " leaves";
    os << ": refused before the search (query in smaller batches or with a smaller k)";
    throw Error(os.str());
  }
}

void check_radius_memory(std::size_t n, std::size_t entries, bool examined, int copies, std::size_t device_bytes,
                         const std::string& method) {
  const double per_query = double(n) * (16.0 + (examined ? 4.0 : 0.0)) + 8.0;
  const double bytes = per_query * copies + (copies > 1 ? 20.0 * double(n) : 0.0) + double(entries) * 16.0 +
                       double(device_bytes);
  if (bytes < double(std::size_t(64) << 20)) return;  // small: not worth the /proc reads
  std::string bound;
  const std::uint64_t can = allocatable_for(bytes, &bound);
  if (bytes > double(std::numeric_limits<std::size_t>::max() / 2) || bytes > double(can)) {
    std::ostringstream os;
    os << method << " radius search: the radius result needs " << gigabytes(bytes) << " (n = " << n << " queries";
    if (entries) os << ", " << entries << " points within the radius counted by the count pass (ids and squared "
                    << "distances, twice: the reordered or re-checked copy)";
    else os << ": offsets and counts" << (copies > 1 ? ", twice for the Hilbert order" : "");
    if (device_bytes) os << ", " << gigabytes(double(device_bytes)) << " of device buffers";
    os << ")";
    if (can != std::numeric_limits<std::uint64_t>::max()) os << ", more than the " << gigabytes(double(can)) << " that " << bound << " leaves";
    os << (entries ? ": refused before any of them is fetched" : ": refused before the search")
       << " (query in smaller batches, with a smaller radius or with max_results)";
    throw Error(os.str());
  }
}

}  // namespace bhcl
