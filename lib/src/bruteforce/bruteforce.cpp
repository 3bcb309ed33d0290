#include "blockhash_cl/bruteforce.hpp"

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <map>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"

namespace bhcl {

BruteForceIndex::BruteForceIndex(std::shared_ptr<Runtime> runtime, const float* points,
                                 std::size_t n_points)
    : Index(std::move(runtime), n_points) {
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> storage;
  const float* pts = prepare_points(points, n_points, storage);
  // w = the point's id (int bits): the kernels rank and report by it, so that the ids stay stable
  // when updates compact the array (kept in ascending id order: ties still go to the lower id).
  host_.resize(n_points);
  for (std::size_t i = 0; i < n_points; ++i)
    host_[i] = HostPoint{pts[3 * i], pts[3 * i + 1], pts[3 * i + 2], static_cast<std::int32_t>(i)};
  upload_from(0, true);
  set_build_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}

// The device array from entry `from` on; a new buffer (capacity grown by half) when the points no
// longer fit, so that a growing sequence reallocates O(log) times.
void BruteForceIndex::upload_from(std::size_t from, bool fresh) {
  const auto& rt = runtime_ptr();
  const std::size_t bytes = std::max<std::size_t>(host_.size(), 1) * sizeof(HostPoint);
  if (fresh || !points_() || bytes > cap_bytes_) {
    const std::size_t cap = fresh ? bytes : std::max(bytes, cap_bytes_ + cap_bytes_ / 2);
    cl_int err = CL_SUCCESS;
    points_ = cl::Buffer(rt->context(), CL_MEM_READ_ONLY, cap, nullptr, &err);
    check_cl(err, "clCreateBuffer", "bruteforce points, " + std::to_string(cap) + " bytes");
    cap_bytes_ = cap;
    from = 0;
  }
  if (host_.empty() || from >= host_.size()) return;
  check_cl(rt->queue().enqueueWriteBuffer(points_, CL_TRUE, from * sizeof(HostPoint),
                                          (host_.size() - from) * sizeof(HostPoint), host_.data() + from),
           "clEnqueueWriteBuffer", "bruteforce points");
}

// Updates: appended (ids are issued in ascending order) or compacted in place, order kept, and
// only the changed tail of the device array written. No structure to rebuild.
void BruteForceIndex::insert_points(const float*, const float* scaled, std::size_t n, std::int32_t first) {
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "bruteforce insert");
  const std::size_t at = host_.size();
  host_.resize(at + n);
  for (std::size_t i = 0; i < n; ++i)
    host_[at + i] = HostPoint{scaled[3 * i], scaled[3 * i + 1], scaled[3 * i + 2], first + static_cast<std::int32_t>(i)};
  try {
    upload_from(at, false);
  } catch (...) {
    host_.resize(at);
    throw;
  }
}

void BruteForceIndex::remove_points(const std::int32_t* ids, std::size_t n) {
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "bruteforce remove");
  // ids ascending, host_ ascending by id: one merge pass.
  const auto lower = std::lower_bound(host_.begin(), host_.end(), ids[0],
                                      [](const HostPoint& p, std::int32_t id) { return p.id < id; });
  const std::size_t from = std::size_t(lower - host_.begin());
  std::size_t w = from, j = 0;
  for (std::size_t i = from; i < host_.size(); ++i) {
    if (j < n && host_[i].id == ids[j]) {
      ++j;
      continue;
    }
    host_[w++] = host_[i];
  }
  if (j != n) throw Error("bruteforce: remove: an id was not stored (internal)");
  host_.resize(w);
  upload_from(from, false);
}

cl::Event BruteForceIndex::enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                         std::size_t first, std::size_t count,
                                         const ResultBuffers& out, const SearchParams& params,
                                         std::size_t local_size,
                                         const std::vector<cl::Event>* wait) const {
  int kmax = kmax_variant(params.k);
  cl::Kernel kernel = runtime().kernel(
      "bruteforce_knn.cl", "bruteforce_knn",
      detail::kernel_build_options("bruteforce_knn.cl", {{"BHCL_KMAX", kmax}}, params.kernel_defines));
  detail::KernelArgs args(kernel, "bruteforce_knn");
  args.add(points_)
      .add(cl_uint(host_.size()))
      .add_queries(queries, first, count, params)
      .add_results(out)
      .add_local(local_size * sizeof(cl_float4));
  return detail::launch_1d(queue, kernel, count, local_size, wait, "bruteforce_knn");
}

cl::Event BruteForceIndex::enqueue_radius_batch(const cl::CommandQueue& queue,
                                                const cl::Buffer& queries, std::size_t first,
                                                std::size_t count, float r2, int pass,
                                                const RadiusBuffers& out, const RadiusParams& params,
                                                std::size_t local_size,
                                                const std::vector<cl::Event>* wait) const {
  cl::Kernel kernel = runtime().kernel("bruteforce_radius.cl", "bruteforce_radius",
                                       detail::kernel_build_options("bruteforce_radius.cl", {}, params.kernel_defines));
  detail::KernelArgs args(kernel, "bruteforce_radius");
  args.add(points_).add(cl_uint(host_.size())).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, "bruteforce_radius");
}

}  // namespace bhcl
