#include "blockhash_cl/bruteforce.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>
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
  // Room for inserts of up to an eighth (2 B per point): the first insert after a build appends
  // instead of moving every point (that move, and the upload after it, cost as much as the build).
  host_.reserve(n_points + n_points / 8);
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

// Updates: appended (ids are issued in ascending order) or compacted in place, order kept, and
// only the changed tail of the device array written. No structure to rebuild.
void BruteForceIndex::insert_points(const float*, const float* scaled, std::size_t n, std::int32_t first) {
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "bruteforce insert");
  const std::size_t at = host_.size();
  // Past the room: the room a fresh build of the result keeps (an eighth), at least an eighth
  // more than now (geometric: O(1) moves per point over any sequence). Not std::vector's
  // doubling: the allocator serves a block of a fresh build's size from the memory a freed index
  // left, where a doubled one takes fresh pages, and their faults cost more than the build
  // (16 MB: 80-120 ms of faults against 1 ms reused, measured on this machine under load).
  if (at + n > host_.capacity())
    host_.reserve(std::max(at + n + (at + n) / 8, host_.capacity() + host_.capacity() / 8));
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

// A remove: the points become holes in place (NaN coordinates: no distance comparison accepts
// one, so neither kernel returns it, at any radius), written back as the span they touch (nothing
// on an in-place device); past an eighth of holes one stable compaction drops them all, order kept.
void BruteForceIndex::remove_points(const std::int32_t* ids, std::size_t n) {
  check_cl(runtime_ptr()->queue().finish(), "clFinish", "bruteforce remove");
  // ids ascending, host_ ascending by distinct ids from 0: the entry of an id lies at or before
  // the id's own number and after the previous id's entry, so a binary search in that range finds
  // it (a few steps while few were compacted away; a walk over every entry read 16 MB at 1M).
  // Before any compaction an id's entry is the id's own number: one read, no search.
  std::vector<std::size_t> at(n);
  {
    std::size_t lo = 0;
    constexpr std::size_t kAhead = 64;  // each entry a cache miss: prefetched some ids ahead
    for (std::size_t j = 0; j < n; ++j) {
      if (j + kAhead < n && std::size_t(ids[j + kAhead]) < host_.size()) __builtin_prefetch(&host_[std::size_t(ids[j + kAhead])], 1);
      const std::size_t own = std::size_t(ids[j]);
      if (own < host_.size() && host_[own].id == ids[j] && own >= lo && !std::isnan(host_[own].x)) {
        at[j] = own;
        lo = own + 1;
        continue;
      }
      const std::size_t hi = std::min(host_.size(), std::size_t(ids[j]) + 1);
      const std::size_t i = std::size_t(std::lower_bound(host_.begin() + std::ptrdiff_t(std::min(lo, hi)), host_.begin() + std::ptrdiff_t(hi), ids[j],
                                                         [](const HostPoint& p, std::int32_t id) { return p.id < id; }) -
                                        host_.begin());
      if (i == hi || host_[i].id != ids[j] || std::isnan(host_[i].x))
        throw Error("bruteforce: remove: id " + std::to_string(ids[j]) + " was not stored (internal)");
      at[j] = i;
      lo = i + 1;
    }
  }
  const float nan = std::numeric_limits<float>::quiet_NaN();
  if (8 * (holes_ + n) <= host_.size()) {
    for (std::size_t i : at) host_[i].x = host_[i].y = host_[i].z = nan;
    holes_ += n;
    if (!runtime_ptr()->quirks().host_ptr_in_place) {
      const std::size_t lo = at.front(), len = at.back() - lo + 1;
      check_cl(runtime_ptr()->queue().enqueueWriteBuffer(points_, CL_TRUE, lo * sizeof(HostPoint), len * sizeof(HostPoint),
                                                         host_.data() + lo),
               "clEnqueueWriteBuffer", "bruteforce points (holes)");
    }
    return;
  }
  for (std::size_t i : at) host_[i].x = nan;
  std::size_t w = 0;
  for (std::size_t i = 0; i < host_.size(); ++i)
    if (!std::isnan(host_[i].x)) host_[w++] = host_[i];
  host_.resize(w);
  holes_ = 0;
  upload_from(0, false);
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
