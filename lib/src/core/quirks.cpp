// The quirks list: what differs between the OpenCL drivers we run on, decided once per device.
#include "blockhash_cl/quirks.hpp"

#include <cstdlib>
#include <string>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/runtime.hpp"

namespace bhcl {

Quirks quirks_for(const DeviceInfo& device) {
  DeviceInfo info = device;
  // BHCL_QUIRKS_AS=nvidia: decide the quirks (and so the kernels' defines) as for an NVIDIA GPU
  // whatever the device; for tools that compile the kernels for a GPU offline
  // (bench/gpu_kernel_table.sh). Results are the same; only speed differs.
  if (const char* as = std::getenv("BHCL_QUIRKS_AS"); as && *as) {
    if (std::string(as) != "nvidia")
      throw Error(std::string("BHCL_QUIRKS_AS='") + as + "' is not known: the one value is 'nvidia'");
    info.is_pocl = false;
    info.is_nvidia = true;
    info.type = CL_DEVICE_TYPE_GPU;
  }
  Quirks q;
  if (info.is_pocl) {
    // PoCL 3.1 compiles machine code per kernel and local size at the first enqueue: each kernel
    // variant is warmed up by a launch on Runtime::warm_queue (Index::warm_up), on every device alike.
    // On the pthread device a work-group runs as one loop on one core: 64 items amortise the
    // per-group cost while keeping enough groups for every core.
    q.default_local_size = 64;
    q.max_launch_items = 65535;
    q.description = "pocl: compiles at first launch (warm-up launch before timing), launches under 65535 items";
  } else if (info.is_nvidia) {
    // NVIDIA's driver compiles at clBuildProgram. 64 items = 2 warps a group (the private top-k
    // list's registers are per work-item: the group size does not change them).
    q.default_local_size = 64;
    q.description = "nvidia: none";
  } else {
    q.description = "none known";
  }
  // CPU devices (PoCL's pthread device, Intel's CPU runtime) vectorise explicit float16 scans.
  q.vector_scan = (info.type & CL_DEVICE_TYPE_CPU) != 0;
  if (q.vector_scan) q.description += "; cpu: float16 block scans";
  // PoCL's CPU device keeps a CL_MEM_USE_HOST_PTR buffer in the host's memory (measured: a
  // kernel's writes show in the host array before any map, and the map returns the host pointer).
  q.host_ptr_in_place = info.is_pocl && (info.type & CL_DEVICE_TYPE_CPU) != 0;
  if (q.host_ptr_in_place) q.description += "; pocl cpu: host arrays read in place";
  if (info.max_work_group_size && q.default_local_size > info.max_work_group_size)
    q.default_local_size = info.max_work_group_size;
  return q;
}

}  // namespace bhcl
