#include "core/device_util.hpp"

#include <algorithm>

namespace bhcl::detail {

cl::Buffer upload_bytes(const std::shared_ptr<Runtime>& rt, const void* data, std::size_t bytes,
                        const std::string& what) {
  cl_int err = CL_SUCCESS;
  cl::Buffer b(rt->context(), CL_MEM_READ_ONLY | CL_MEM_COPY_HOST_PTR, bytes,
               const_cast<void*>(data), &err);
  check_cl(err, "clCreateBuffer", what + ", " + std::to_string(bytes) + " bytes");
  return b;
}

cl::Buffer device_buffer(const Runtime& rt, std::size_t bytes, const std::string& what) {
  cl_int err = CL_SUCCESS;
  cl::Buffer b(rt.context(), CL_MEM_READ_WRITE, std::max<std::size_t>(bytes, 4), nullptr, &err);
  check_cl(err, "clCreateBuffer", what + ", " + std::to_string(bytes) + " bytes");
  return b;
}

cl::Buffer upload_points4(const std::shared_ptr<Runtime>& rt, const float* xyz, std::size_t n,
                          const std::string& what) {
  std::vector<cl_float4> p(std::max<std::size_t>(n, 1));
  for (std::size_t i = 0; i < n; ++i) {
    p[i].s[0] = xyz[3 * i];
    p[i].s[1] = xyz[3 * i + 1];
    p[i].s[2] = xyz[3 * i + 2];
    p[i].s[3] = 0.0f;
  }
  return upload_bytes(rt, p.data(), p.size() * sizeof(cl_float4), what);
}

cl::Event launch_1d(const cl::CommandQueue& queue, const cl::Kernel& kernel, std::size_t count,
                    std::size_t local_size, const std::vector<cl::Event>* wait, const char* name) {
  std::size_t groups = std::max<std::size_t>(1, (count + local_size - 1) / local_size);
  cl::Event e;
  check_cl(queue.enqueueNDRangeKernel(kernel, cl::NullRange, cl::NDRange(groups * local_size),
                                      cl::NDRange(local_size), wait, &e),
           "clEnqueueNDRangeKernel",
           std::string(name) + ", global " + std::to_string(groups * local_size) + ", local " +
               std::to_string(local_size));
  return e;
}

std::size_t items_per_launch(std::size_t wanted, std::size_t local, std::size_t limit) {
  if (local && limit > local) wanted = std::min(wanted, (limit - 1) / local * local);  // strictly below it
  return std::max<std::size_t>(wanted, 1);
}

cl::Event one_event(const cl::CommandQueue& queue, std::vector<cl::Event>& events, const std::string& what) {
  if (events.size() == 1) return events.front();
  cl::Event all;
  check_cl(queue.enqueueMarkerWithWaitList(&events, &all), "clEnqueueMarkerWithWaitList", what);
  return all;
}

cl::Event launch_1d_split(const cl::CommandQueue& queue, cl::Kernel& kernel, cl_uint first_arg, std::size_t count,
                          std::size_t local_size, std::size_t max_items, const std::vector<cl::Event>* wait,
                          const char* name) {
  local_size = std::max<std::size_t>(local_size, 1);
  const std::size_t per = items_per_launch(count, local_size, max_items);
  std::vector<cl::Event> parts;
  std::size_t first = 0;
  do {
    check_cl(kernel.setArg(first_arg, cl_ulong(first)), "clSetKernelArg", std::string(name) + " first item");
    parts.push_back(launch_1d(queue, kernel, std::min(per, count - first), local_size, wait, name));
    first += per;
  } while (first < count);
  return one_event(queue, parts, name);
}

}  // namespace bhcl::detail
