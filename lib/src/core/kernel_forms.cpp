// The grid kNN kernel's forms per device (kernel_forms.hpp): the measured table and the choice.
#include "blockhash_cl/kernel_forms.hpp"

#include <cstdlib>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/runtime.hpp"

namespace bhcl::detail {

const std::vector<GridKernelForm>& grid_kernel_forms() {
  // name, match, measured, vtopk, prefetch, row_cap, walk_cap, fill_sort, prefetch_lines,
  // prefetch_ring_from, local_size, cell_target
  static const std::vector<GridKernelForm> rows = {
      {"cpu-avx512", "cpu-avx512",
       "AMD EPYC, PoCL 3.1 pthread-skylake-avx512, 2 threads: bench/results/harness/tune_avx512.txt "
       "(bench/tune_kernel.sh, 3 rounds, 12 rows): no candidate one change away 3 % ahead on the median "
       "without a row 10 % behind, so the AVX2 row's values stand (best: fill0 1.045, lines4 1.047); "
       "work-group 16 / 32 / 128 against 64: 0.999 / 1.003 / 0.998, cell population 16 / 32 / 48 "
       "against 24: 0.950 / 0.910 / 0.954 (bench/results/harness/tune_cells_local_avx512.txt); "
       "Intel Xeon (Sapphire Rapids class), the same PoCL target, session 15's kernel: "
       "bench/results/harness/tune_intel_avx512.txt (3 rounds, 12 rows): no candidate wins either "
       "(best: cells48 1.046 with a row 10 % behind, local16 1.023); at k <= 8 (session 16, "
       "bench/results/harness/k1_ring_intel_s16.txt, 7 rounds, 12 rows at k = 1 and 8): the home "
       "cell's prefetch alone against the 9 rows 1.14x on the median, 0.94-1.70x (k = 1 sorted: "
       "Autzen 1.16 -> 1.56x the kd-tree kernel, uniform 1.26 -> 1.50x, Cornell 1.47 -> 1.68x), "
       "so the 9 rows from the k <= 16 variant up",
       true, 2, 32, 32, -1, -1, 16, 0, 24.0},
      {"cpu-avx2", "cpu",
       "AMD EPYC, PoCL 3.1 pthread-haswell (AVX2), 2 threads: the last round's perf_harness rows "
       "(docs/PERFORMANCE.md); the far walk's queue on the AVX-512 machine (bench/results/far); "
       "the 9 rows' prefetch at every k (the home cell's alone at k <= 8 not measured on AVX2)",
       true, 2, 32, 32, -1, -1, 0, 0, 24.0},
      {"gpu-nvidia", "gpu-nvidia",
       "sm_90 by ptxas (bench/gpu_kernel_table.sh): no private arrays, 46 registers, 144 B / 528 B "
       "of stack at k <= 16 / 64, no spills; not timed on a GPU yet",
       false, 0, 0, 0, -1, -1, 0, 0, 24.0},
      {"safe", "any", "no measurement: the scalar list, no prefetch, no private arrays (any OpenCL device)",
       false, 0, 0, 0, -1, -1, 0, 0, 24.0},
  };
  return rows;
}

namespace {

bool contains(const std::string& s, const char* part) { return s.find(part) != std::string::npos; }

// PoCL's LLVM target CPUs with AVX-512 (the ones its CPU device reports on these machines).
bool isa_has_avx512(const std::string& isa) {
  for (const char* cpu : {"avx512", "cascadelake", "cooperlake", "icelake", "tigerlake", "sapphirerapids",
                          "graniterapids", "emeraldrapids", "znver4", "znver5", "x86-64-v4"})
    if (contains(isa, cpu)) return true;
  return false;
}

bool serves(const GridKernelForm& f, const DeviceInfo& d) {
  const std::string m = f.match;
  const bool cpu = (d.type & CL_DEVICE_TYPE_CPU) != 0;
  if (m == "any") return true;
  if (m == "cpu") return cpu;
  if (m == "cpu-avx512") return cpu && isa_has_avx512(device_isa(d));
  if (m == "gpu-nvidia") return d.is_nvidia && (d.type & CL_DEVICE_TYPE_GPU) != 0;
  throw Error(std::string("kernel forms: row '") + f.name + "' has an unknown match '" + m + "'");
}

}  // namespace

std::string device_isa(const DeviceInfo& d) {
  if (d.type & CL_DEVICE_TYPE_GPU) return d.is_nvidia ? "gpu-nvidia" : "gpu-" + d.device_vendor;
  // PoCL's CPU device is named "cpu-<target>-<model>" (PoCL 4+) or "pthread-<target>-<model>".
  if (!d.is_pocl) return "";
  // Its version string ends in the LLVM triple and CPU: "... HSTR: pthread-x86_64-pc-linux-gnu-skylake-avx512".
  if (const std::size_t h = d.device_version.find("HSTR:"); h != std::string::npos) {
    const std::size_t g = d.device_version.find("-gnu-", h);
    if (g != std::string::npos) {
      const std::size_t b = g + 5, e = d.device_version.find(' ', b);
      return d.device_version.substr(b, e == std::string::npos ? std::string::npos : e - b);
    }
  }
  for (const char* prefix : {"pthread-", "cpu-"}) {
    const std::string p = prefix;
    if (d.device_name.compare(0, p.size(), p) != 0) continue;
    const std::string rest = d.device_name.substr(p.size());
    // The target may hold dashes ("skylake-avx512"); the model starts at its first capital or digit run
    // after a dash that no LLVM CPU name has ("AMD", "Intel", "13th"): cut at the first "-X" with X upper-case.
    for (std::size_t i = 0; i + 1 < rest.size(); ++i)
      if (rest[i] == '-' && (rest[i + 1] >= 'A' && rest[i + 1] <= 'Z')) return rest.substr(0, i);
    return rest;
  }
  return "";
}

const GridKernelForm& grid_kernel_form(const DeviceInfo& d) {
  const auto& rows = grid_kernel_forms();
  if (const char* forced = std::getenv("BHCL_KERNEL_FORM"); forced && *forced) {
    std::string names;
    for (const GridKernelForm& f : rows) {
      if (f.name == std::string(forced)) return f;
      names += std::string(names.empty() ? "" : ", ") + f.name;
    }
    throw Error(std::string("BHCL_KERNEL_FORM='") + forced + "' is not a kernel form: the rows are " + names);
  }
  for (const GridKernelForm& f : rows)
    if (serves(f, d)) return f;
  return rows.back();
}

}  // namespace bhcl::detail
