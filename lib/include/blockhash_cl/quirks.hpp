// Driver quirks, in one place rather than as scattered conditions in the dispatch code.
#pragma once

#include <cstddef>
#include <string>

namespace bhcl {

struct DeviceInfo;

struct Quirks {
  // Work-group size used when the caller does not set one.
  std::size_t default_local_size = 64;
  // Block scans as float16 vectors with an any() skip (CPU compilers vectorise them; on a GPU the
  // scalar loop is the better form). Results are the same either way.
  bool vector_scan = false;
  // Buffers made with CL_MEM_USE_HOST_PTR are the host memory itself (no copy at creation, none
  // at a map): PoCL's CPU device. The grid layout then lets the device read its host arrays in
  // place instead of copying them (16 MB per 1M points, 10-20 % of a rebuild).
  bool host_ptr_in_place = false;
  // Work-items per launch (per dimension) below which the driver compiles a kernel of its own
  // (0: no such limit): every launch is kept below it, so that the warm-up's variant is the one
  // that runs. PoCL 3.1 specialises each kernel for grids narrower than 65535 items ("smallgrid"
  // in its kernel cache) and compiled the other variant, 5-6 s for the grid kernel, at the first
  // launch of more than 65k queries, outside the warm-up and the stats' compile time. Speed is
  // about the same split or not (kernel time of one launch over the split's, one process, AVX-512:
  // 1.054 / 1.003 at k = 10 / 50 on uniform 1M with 1M queries, 0.979 on two clusters with 100k).
  std::size_t max_launch_items = 0;
  // Human-readable list of the quirks that apply, for `bhcl devices` and the stats.
  std::string description;
};

Quirks quirks_for(const DeviceInfo& info);

}  // namespace bhcl
