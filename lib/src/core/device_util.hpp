// Small pieces the device methods share: uploads, argument setting with error context, launches.
#pragma once

#include <CL/opencl.hpp>

#include <cmath>
#include <cstddef>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/runtime.hpp"

namespace bhcl::detail {

// Copies n x 3 floats to a new device buffer of float4 (w = 0). Blocks until done.
cl::Buffer upload_points4(const std::shared_ptr<Runtime>& rt, const float* xyz, std::size_t n,
                          const std::string& what);

// A read-only device buffer holding a copy of `bytes` bytes of host data (blocking).
cl::Buffer upload_bytes(const std::shared_ptr<Runtime>& rt, const void* data, std::size_t bytes,
                        const std::string& what);

// A read-write device buffer of `bytes` bytes (at least 4: a zero-size buffer is invalid in
// OpenCL); a failure names `what` and the size asked for.
cl::Buffer device_buffer(const Runtime& rt, std::size_t bytes, const std::string& what);

template <typename T>
cl::Buffer upload_vector(const std::shared_ptr<Runtime>& rt, const std::vector<T>& v,
                         const std::string& what) {
  // A zero-size buffer is invalid in OpenCL: keep one element.
  static const T zero{};
  return upload_bytes(rt, v.empty() ? &zero : v.data(), std::max<std::size_t>(1, v.size()) * sizeof(T), what);
}

// r*r, with +inf for an infinite radius.
inline float squared_radius(float r) {
  return std::isinf(r) ? std::numeric_limits<float>::infinity() : r * r;
}

// Sets kernel arguments in order; a failure names the kernel and the argument index.
class KernelArgs {
 public:
  KernelArgs(cl::Kernel& k, const char* name) : k_(k), name_(name) {}
  template <typename T>
  KernelArgs& add(const T& value) {
    check_cl(k_.setArg(i_, value), "clSetKernelArg", name_ + " argument " + std::to_string(i_));
    ++i_;
    return *this;
  }
  // What every kNN kernel takes, in this order: the query buffer, the first row, the count of
  // rows, k and the squared radius.
  KernelArgs& add_queries(const cl::Buffer& queries, std::size_t first, std::size_t count,
                          const SearchParams& p) {
    return add(queries).add(cl_ulong(first)).add(cl_uint(count)).add(cl_uint(p.k)).add(squared_radius(p.max_radius));
  }
  // The result buffers: ids, squared distances, counts, and the result rows (ResultBuffers::rows;
  // counts stands in, unread, when there are none: a valid argument on every platform).
  KernelArgs& add_results(const ResultBuffers& out) {
    const bool remap = out.rows() != nullptr;
    return add(out.ids).add(out.dist2).add(out.counts).add(remap ? out.rows : out.counts).add(cl_uint(remap ? 1 : 0));
  }
  // What every radius kernel ends with (kernels/radius_common.h, BHCL_RADIUS_PARAMS). The
  // examined buffer is set even when not wanted (a valid argument; the kernel does not write it).
  KernelArgs& add_radius(const cl::Buffer& queries, std::size_t first, std::size_t count, float r2,
                         int pass, const RadiusBuffers& out, bool want_examined) {
    return add(queries).add(cl_ulong(first)).add(cl_uint(count)).add(r2).add(cl_uint(pass))
        .add(out.offsets).add(out.counts).add(out.ids).add(out.dist2)
        .add(want_examined ? out.examined : out.counts).add(cl_uint(want_examined ? 1 : 0));
  }
  KernelArgs& add_local(std::size_t bytes) {
    check_cl(k_.setArg(i_, cl::Local(bytes)), "clSetKernelArg",
             name_ + " local argument " + std::to_string(i_));
    ++i_;
    return *this;
  }

 private:
  cl::Kernel& k_;
  std::string name_;
  cl_uint i_ = 0;
};

// Launches count work-items (rounded up to the local size; at least one group).
cl::Event launch_1d(const cl::CommandQueue& queue, const cl::Kernel& kernel, std::size_t count,
                    std::size_t local_size, const std::vector<cl::Event>* wait, const char* name);

// The work-items a launch takes: at most `wanted`, and below the driver's launch limit
// (Quirks::max_launch_items; 0: none) in whole groups of `local`; >= 1. PoCL compiles a second
// variant of a kernel, inside the launch, for 65535 items or more.
std::size_t items_per_launch(std::size_t wanted, std::size_t local, std::size_t limit);

// One event for enqueued commands: the only one, or a marker on all of them (none: on the queue's
// earlier commands), so that it means "all done" on any queue.
cl::Event one_event(const cl::CommandQueue& queue, std::vector<cl::Event>& events, const std::string& what);

// launch_1d for a kernel whose argument first_arg (a ulong) is the index of its first item (item
// i of a launch is first + get_global_id(0)): in launches of items_per_launch(count, local,
// max_items), each waiting for `wait`. Returns one_event of them.
cl::Event launch_1d_split(const cl::CommandQueue& queue, cl::Kernel& kernel, cl_uint first_arg, std::size_t count,
                          std::size_t local_size, std::size_t max_items, const std::vector<cl::Event>* wait,
                          const char* name);

}  // namespace bhcl::detail
