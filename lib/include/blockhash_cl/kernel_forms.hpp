// The grid kNN kernel's form per device, as a measured table (as CLBlast keeps per-device tuning
// values and Embree builds per ISA): which list, prefetch, gathered rings, far walk, work-group
// size and cell population a device runs, chosen from what the device reports, with a safe row
// for devices nobody measured.
// bench/tune_kernel.sh measures a device's candidates (perf_harness runs) and prints the winner
// as a row of this table (lib/src/core/kernel_forms.cpp), so a user on a new CPU can add theirs.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace bhcl {
struct DeviceInfo;
}

namespace bhcl::detail {

struct GridKernelForm {
  const char* name;      // the row's name ("cpu-avx512"); BHCL_KERNEL_FORM=name forces it
  const char* match;     // the devices it serves: "cpu-avx512", "cpu", "gpu-nvidia" or "any"
  const char* measured;  // where and how the row was measured, and what it gave
  bool vtopk;            // BHCL_GRID_VTOPK: the top-k list in vector registers (k <= 64)
  int prefetch;          // BHCL_GRID_PREFETCH: 0 none, 2 clang's __builtin_prefetch
  std::uint32_t row_cap;   // BHCL_GRID_ROWCAP: runs of a ring gathered, scanned nearest first
  std::uint32_t walk_cap;  // BHCL_GRID_WALKCAP: the far walk's best-first queue (0: depth-first)
  int fill_sort;         // BHCL_GRID_FILLSORT: -1 the kernel's default (sorted fill past 16)
  int prefetch_lines;    // BHCL_GRID_PREFETCH_LINES: -1 the kernel's default
  // BHCL_GRID_PREFETCH_RING per k variant: the 9 rows around the home cell prefetched from this
  // BHCL_KMAX up, only the home cell's below it (0: the 9 rows at every k). At small k a query's
  // search is short and the 9 rows' lookups cost more than the misses they hide.
  int prefetch_ring_from;
  std::uint32_t local_size;  // the grid kernels' work-group size where the caller sets none (0: the quirks')
  double cell_target;        // the grid's mean cell population where the build sets none (target_cell_points)
};

// The rows, most specific first; the last is the safe default.
const std::vector<GridKernelForm>& grid_kernel_forms();

// The device's ISA as its driver names it: PoCL's LLVM target CPU ("skylake-avx512", "haswell",
// "znver3"; from the device name "pthread-<cpu>-<model>"), "gpu-<vendor>" for a GPU, else "".
std::string device_isa(const DeviceInfo& d);

// The row a device runs: BHCL_KERNEL_FORM if set (a row's name, else an error listing them),
// else the first row whose match the device meets.
const GridKernelForm& grid_kernel_form(const DeviceInfo& d);

}  // namespace bhcl::detail
