// The grid kernel's forms table (lib/src/core/kernel_forms.cpp): the ISA read from what PoCL
// reports, the row each kind of device gets, BHCL_KERNEL_FORM forcing a row, and every row's
// kernel building and answering exactly (the forms differ in speed only).
#include <cstdlib>

#include "blockhash_cl/kernel_forms.hpp"
#include "test_util.hpp"

using namespace bhcl;

namespace {

DeviceInfo pocl_cpu(const std::string& name, const std::string& version) {
  DeviceInfo d;
  d.is_pocl = true;
  d.type = CL_DEVICE_TYPE_CPU;
  d.device_name = name;
  d.device_version = version;
  return d;
}

struct ScopedEnv {
  std::string name;
  ScopedEnv(const char* n, const char* v) : name(n) { ::setenv(n, v, 1); }
  ~ScopedEnv() { ::unsetenv(name.c_str()); }
};

}  // namespace

TEST_CASE("kernel forms: the ISA from PoCL's version string or device name, and the row it gets") {
  const DeviceInfo avx512 = pocl_cpu("pthread-skylake-avx512-AMD EPYC 9654 96-Core Processor",
                                     "OpenCL 3.0 PoCL HSTR: pthread-x86_64-pc-linux-gnu-skylake-avx512");
  CHECK(detail::device_isa(avx512) == "skylake-avx512");
  CHECK(std::string(detail::grid_kernel_form(avx512).name) == "cpu-avx512");
  // No HSTR: from the name, the target up to the model's first capital.
  const DeviceInfo avx2 = pocl_cpu("pthread-haswell-AMD EPYC 7B13", "OpenCL 3.0 PoCL");
  CHECK(detail::device_isa(avx2) == "haswell");
  CHECK(std::string(detail::grid_kernel_form(avx2).name) == "cpu-avx2");
  CHECK(std::string(detail::grid_kernel_form(pocl_cpu("cpu-znver4-AMD Ryzen", "")).name) == "cpu-avx512");
  DeviceInfo gpu;
  gpu.is_nvidia = true;
  gpu.type = CL_DEVICE_TYPE_GPU;
  CHECK(std::string(detail::grid_kernel_form(gpu).name) == "gpu-nvidia");
  DeviceInfo other;
  other.type = CL_DEVICE_TYPE_ACCELERATOR;
  CHECK(std::string(detail::grid_kernel_form(other).name) == "safe");
  // The GPU and safe rows keep no private arrays (the sm_90 stack the GPU table checks).
  for (const DeviceInfo* d : {&gpu, &other}) {
    const detail::GridKernelForm& f = detail::grid_kernel_form(*d);
    CHECK(f.row_cap == 0);
    CHECK(f.walk_cap == 0);
    CHECK(!f.vtopk);
  }
}

TEST_CASE("kernel forms: BHCL_KERNEL_FORM forces a row by name, and an unknown name is refused with the list") {
  const DeviceInfo avx2 = pocl_cpu("pthread-haswell-AMD EPYC 7B13", "");
  {
    ScopedEnv e("BHCL_KERNEL_FORM", "safe");
    CHECK(std::string(detail::grid_kernel_form(avx2).name) == "safe");
  }
  ScopedEnv e("BHCL_KERNEL_FORM", "avx1024");
  CHECK_THROWS_WITH_AS(detail::grid_kernel_form(avx2),
                       doctest::Contains("BHCL_KERNEL_FORM='avx1024' is not a kernel form: the rows are cpu-avx512"), Error);
}

TEST_CASE("kernel forms: every row's kernel gives the exact rows (grid_forms_vs_bruteforce)") {
  const auto pts = datasets::clustered(20000, 3, 8, 0.01f);
  auto qs = datasets::uniform(400, 9, -0.5f, 1.5f);  // on the data and far from it: rings and walk
  const auto on = datasets::clustered(400, 4, 8, 0.01f);
  qs.insert(qs.end(), on.begin(), on.end());
  for (const detail::GridKernelForm& f : detail::grid_kernel_forms()) {
    CAPTURE(f.name);
    ScopedEnv e("BHCL_KERNEL_FORM", f.name);
    auto index = BlockHashIndex::build(test::runtime(), pts.data(), pts.size() / 3);
    // The row's cell population is the build's aim where the caller sets none (the secant tunes
    // the point-weighted mean to within a few per cent of it), and its work-group size the launch's.
    CHECK(index->info().mean_cell_points == doctest::Approx(f.cell_target).epsilon(0.15));
    const std::size_t quirks = test::runtime()->quirks().default_local_size;
    CHECK(index->local_size_for(SearchParams{}) == (f.local_size ? f.local_size : quirks));
    for (int k : {1, 16, 50}) {
      CAPTURE(k);
      SearchParams p = test::knn_params(k);
      p.A = INFINITY;
      const KnnResult got = index->query(qs, p);
      const KnnResult ref = reference::knn_float(pts.data(), pts.size() / 3, qs.data(), qs.size() / 3, p);
      test::require_identical(got, ref, std::string("form ") + f.name);
    }
  }
}
