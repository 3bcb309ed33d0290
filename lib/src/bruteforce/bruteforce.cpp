#include "blockhash_cl/bruteforce.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <vector>

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
  // Room for as many points again (address space: a page is faulted in only when an insert
  // writes it): inserts append instead of moving every point (that move, and the upload after it,
  // cost as much as the build; at 1M + 25 % more, the faults of its fresh pages 1.2-1.4x).
  host_.reserve(2 * n_points);
  host_.resize(n_points);
  for (std::size_t i = 0; i < n_points; ++i)
    host_[i] = HostPoint{pts[3 * i], pts[3 * i + 1], pts[3 * i + 2], static_cast<std::int32_t>(i)};
  upload_from(0, true);
  set_build_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}

// The device array from entry `from` on; a new buffer (capacity grown by half) when the points no
// longer fit, so that a growing sequence reallocates O(log) times. On a device that reads host
// memory in place (PoCL's CPU device, Quirks::host_ptr_in_place) the buffer is a view of host_
// itself, made again after every update (host_ may have moved): nothing is copied.
void BruteForceIndex::upload_from(std::size_t from, bool fresh) {
  const auto& rt = runtime_ptr();
  const std::size_t bytes = std::max<std::size_t>(host_.size(), 1) * sizeof(HostPoint);
  if (rt->quirks().host_ptr_in_place && !host_.empty()) {
    cl_int err = CL_SUCCESS;
    points_ = cl::Buffer(rt->context(), CL_MEM_READ_ONLY | CL_MEM_USE_HOST_PTR, bytes, host_.data(), &err);
    check_cl(err, "clCreateBuffer", "bruteforce points (in place), " + std::to_string(bytes) + " bytes");
    cap_bytes_ = bytes;
    return;
  }
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

std::size_t BruteForceIndex::memory_bytes() const {
  return runtime_ptr()->quirks().host_ptr_in_place ? 0 : host_.size() * sizeof(HostPoint);
}

// The removed ids' marks for the kernels, which skip a point whose id is marked (its tile entry
// or its test made NaN: no distance comparison accepts it). Where the device reads host memory in
// place, a view of the index's marks, made again after every update (an insert may move them);
// elsewhere the marks written to a buffer grown by half (ids issued after it read as live).
void BruteForceIndex::upload_removed() {
  const auto& rt = runtime_ptr();
  removed_words_ = removed_word_count();
  if (removed_words_ == 0) return;
  const std::size_t bytes = removed_words_ * 4;
  cl_int err = CL_SUCCESS;
  if (rt->quirks().host_ptr_in_place) {
    removed_ = cl::Buffer(rt->context(), CL_MEM_READ_ONLY | CL_MEM_USE_HOST_PTR, bytes,
                          const_cast<std::uint32_t*>(removed_words()), &err);
    check_cl(err, "clCreateBuffer", "bruteforce removed ids (in place), " + std::to_string(bytes) + " bytes");
    return;
  }
  if (!removed_() || bytes > removed_cap_bytes_) {
    removed_cap_bytes_ = std::max(bytes, removed_cap_bytes_ + removed_cap_bytes_ / 2);
    removed_ = cl::Buffer(rt->context(), CL_MEM_READ_ONLY, removed_cap_bytes_, nullptr, &err);
    check_cl(err, "clCreateBuffer", "bruteforce removed ids, " + std::to_string(removed_cap_bytes_) + " bytes");
  }
  check_cl(rt->queue().enqueueWriteBuffer(removed_, CL_TRUE, 0, bytes, removed_words()), "clEnqueueWriteBuffer",
           "bruteforce removed ids");
}

// Updates: appended (ids are issued in ascending order) or compacted in place, order kept, and
// only the changed tail of the device array written. No structure to rebuild.
void BruteForceIndex::insert_points(const float*, const float* scaled, std::size_t n, std::int32_t first) {
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "bruteforce insert");
  const std::size_t at = host_.size();
  // Past the room (as many points again as the build's): twice the capacity (geometric: O(1)
  // moves per point over any sequence).
  if (at + n > host_.capacity()) host_.reserve(std::max(at + n, 2 * host_.capacity()));
  host_.resize(at + n);
  for (std::size_t i = 0; i < n; ++i)
    host_[at + i] = HostPoint{scaled[3 * i], scaled[3 * i + 1], scaled[3 * i + 2], first + static_cast<std::int32_t>(i)};
  try {
    upload_from(at, false);
    if (runtime_ptr()->quirks().host_ptr_in_place) upload_removed();  // the marks may have moved
  } catch (...) {
    host_.resize(at);
    throw;
  }
}

// A remove: the points stay where they are, skipped by the kernels by their ids' marks (the
// index's, set before this call), so nothing of the point array is read or written (finding and
// overwriting each removed entry with NaN was half of a 10 % remove, a cache miss per id); past an
// eighth of removed points still stored, one stable compaction drops them all, order kept.
void BruteForceIndex::remove_points(const std::int32_t*, std::size_t n) {
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "bruteforce remove");
  holes_ += n;
  if (8 * holes_ > host_.size()) {
    std::size_t w = 0;
    for (std::size_t i = 0; i < host_.size(); ++i)
      if (!id_removed(host_[i].id)) host_[w++] = host_[i];
    host_.resize(w);
    holes_ = 0;
    upload_from(0, false);
  }
  upload_removed();
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
      .add(removed_() ? removed_ : points_)  // points_ stands in, unread, while none was removed
      .add(cl_uint(removed_() ? removed_words_ : 0))
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
  args.add(points_)
      .add(cl_uint(host_.size()))
      .add(removed_() ? removed_ : points_)  // points_ stands in, unread, while none was removed
      .add(cl_uint(removed_() ? removed_words_ : 0))
      .add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, "bruteforce_radius");
}

}  // namespace bhcl
