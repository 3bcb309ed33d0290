#include "blockhash_cl/bruteforce.hpp"

#include <chrono>
#include <map>

#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"

namespace bhcl {

BruteForceIndex::BruteForceIndex(std::shared_ptr<Runtime> runtime, const float* points,
                                 std::size_t n_points)
    : Index(std::move(runtime), n_points) {
  auto t0 = std::chrono::steady_clock::now();
  std::vector<float> storage;
  const float* pts = prepare_points(points, n_points, storage);
  points_ = detail::upload_points4(runtime_ptr(), pts, n_points, "bruteforce points");
  set_build_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
}

cl::Event BruteForceIndex::enqueue_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                         std::size_t first, std::size_t count,
                                         const ResultBuffers& out, const SearchParams& params,
                                         std::size_t local_size,
                                         const std::vector<cl::Event>* wait) const {
  int kmax = kmax_variant(params.k);
  cl::Kernel kernel = runtime().kernel("bruteforce_knn.cl", "bruteforce_knn",
                                       detail::with_defines("-DBHCL_KMAX=" + std::to_string(kmax), params));
  detail::KernelArgs args(kernel, "bruteforce_knn");
  args.add(points_)
      .add(cl_uint(size()))
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
  cl::Kernel kernel = runtime().kernel("bruteforce_radius.cl", "bruteforce_radius", params.kernel_defines);
  detail::KernelArgs args(kernel, "bruteforce_radius");
  args.add(points_).add(cl_uint(size())).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, "bruteforce_radius");
}

}  // namespace bhcl
