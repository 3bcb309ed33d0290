// bhcl devices: the OpenCL platforms and devices, and which one BHCL_DEVICE / default picks.
#include <cstdio>
#include <cstdlib>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/runtime.hpp"
#include "blockhash_cl/kernel_forms.hpp"
#include "cli.hpp"
#include "commands.hpp"

namespace bhcl::cli {
namespace {

void declare_devices(Args& a) {
  a.add_text("device", "show which device this spec picks: P:D, cpu, gpu or a name fragment", "", "SPEC");
}

int run_devices(const Args& args) {
  auto devs = list_devices();
  if (devs.empty()) {
    std::printf("no OpenCL platform or device found (install pocl-opencl-icd; for NVIDIA set "
                "OCL_ICD_VENDORS, see README)\n");
    return 1;
  }
  std::printf("%-5s %-30s %-40s %-5s %4s %9s  %s\n", "spec", "platform", "device", "type", "CU",
              "mem MiB", "version");
  for (const auto& d : devs) {
    std::printf("%zu:%-3zu %-30.30s %-40.40s %-5s %4u %9llu  %s\n", d.platform_index,
                d.device_index, d.platform_name.c_str(), d.device_name.c_str(),
                d.type_name().c_str(), d.compute_units, d.global_mem_bytes >> 20,
                d.device_version.c_str());
  }
  std::string spec = args.str("device", "");
  const char* env = std::getenv("BHCL_DEVICE");
  DeviceInfo pick = select_device(spec);
  std::printf("\nselected (%s): %zu:%zu %s\nquirks: %s\n",
              !spec.empty() ? ("--device " + spec).c_str()
                            : (env && *env ? ("BHCL_DEVICE=" + std::string(env)).c_str() : "default"),
              pick.platform_index, pick.device_index, pick.summary().c_str(),
              quirks_for(pick).description.c_str());
  const detail::GridKernelForm& f = detail::grid_kernel_form(pick);
  std::printf("grid kernel form: %s (isa '%s'; vtopk %d, prefetch %d, row_cap %u, walk_cap %u, fill_sort %d, "
              "prefetch_lines %d, prefetch_ring_from %d, local_size %u, cell_target %g)\n  measured: %s\n",
              f.name, detail::device_isa(pick).c_str(), f.vtopk ? 1 : 0, f.prefetch, f.row_cap, f.walk_cap, f.fill_sort,
              f.prefetch_lines, f.prefetch_ring_from, f.local_size, f.cell_target, f.measured);
  const char* cache = std::getenv("POCL_CACHE_DIR");
  std::printf("PoCL kernel cache: %s\n", cache && *cache ? cache : "PoCL's default");
  return 0;
}

RegisterCommand reg_devices("devices", "the OpenCL platforms and devices, and which one is picked",
                            declare_devices, run_devices);

}  // namespace
}  // namespace bhcl::cli
