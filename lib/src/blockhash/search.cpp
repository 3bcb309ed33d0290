// BlockHashIndex's shared search side: the budget, the tuned A, and the host reference's path
// (validation and coordinates); the layouts' checks, kernels and references are their own
// (grid_index.cpp, tables_index.cpp).
#include <algorithm>
#include <cmath>

#include "blockhash/build.hpp"
#include "core/device_util.hpp"
#include "core/kernel_defines.hpp"

namespace bhcl {

std::uint32_t BlockHashIndex::budget(const SearchParams& p) {
  double b = std::ceil(double(p.A) * double(p.k));
  return static_cast<std::uint32_t>(std::min(b, 4294967295.0));
}

std::optional<BlockHashIndex::RecallTuning> BlockHashIndex::recall_tuning(const SearchParams& p) const {
  if (!(p.recall_target > 0)) return std::nullopt;
  if (exact_mode() && p.recall_target >= 1) {  // the exact mode: nothing to tune
    RecallTuning exact;
    exact.A = INFINITY;
    exact.recall = 1;
    exact.reached = true;
    return exact;
  }
  // Tuned without the radius (in whichever coordinates the caller's path holds it): the budget
  // a recall needs does not depend on it.
  auto key = std::make_tuple(p.k, p.neighbour_probes, p.recall_target);
  SearchParams tp = p;
  tp.max_radius = INFINITY;
  ReadLock read(*this);  // before the tuning's lock, as an update takes them (recall.cpp)
  std::lock_guard<std::mutex> lock(tune_mutex_);
  auto it = tuned_.find(key);
  if (it != tuned_.end()) return it->second;
  RecallTuning t = tune_for_recall(p.recall_target, tp);
  tuned_[key] = t;
  return t;
}

float BlockHashIndex::resolved_A(const SearchParams& p) const {
  if (p.recall_target > 0) return recall_tuning(p)->A;  // at a target of 1: the exact mode
  if (p.A == 0) return exact_mode() ? INFINITY : 8.0f;  // the index's default (SearchParams::A)
  return p.A;
}

SearchParams BlockHashIndex::resolved(const SearchParams& p) const {
  SearchParams out = p;
  out.A = resolved_A(p);
  out.recall_target = 0;
  return out;
}

cl::Kernel BlockHashIndex::layout_kernel(const char* name, const detail::DefineValues& defines,
                                         const std::string& caller_defines) const {
  const std::string file = std::string(name) + ".cl";
  return runtime().kernel(file, name, detail::kernel_build_options(file, defines, caller_defines));
}

void BlockHashIndex::add_knn_results(detail::KernelArgs& args, const ResultBuffers& out, bool count_examined) const {
  args.add_results(out).add(count_examined ? out.examined : dummy_).add(cl_uint(count_examined ? 1 : 0));
}

cl::Event BlockHashIndex::enqueue_radius_batch(const cl::CommandQueue& queue, const cl::Buffer& queries,
                                               std::size_t first, std::size_t count, float r2, int pass,
                                               const RadiusBuffers& out, const RadiusParams& params,
                                               std::size_t local_size, const std::vector<cl::Event>* wait) const {
  const RadiusKernel rk = radius_kernel();
  cl::Kernel kernel = layout_kernel(rk.name, rk.defines, params.kernel_defines);
  detail::KernelArgs args(kernel, rk.name);
  add_radius_layout_args(args, params);
  args.add(cl_uint(params.budget)).add_radius(queries, first, count, r2, pass, out, params.count_examined);
  return detail::launch_1d(queue, kernel, count, local_size, wait, rk.name);
}

KnnResult BlockHashIndex::reference_query(const float* queries, std::size_t n,
                                          const SearchParams& params_in,
                                          std::vector<std::int32_t>* examined,
                                          unsigned threads) const {
  check_params(params_in);
  // The same path as query(): the tuned A, queries and radius in the structure's coordinates,
  // distances back in the caller's.
  SearchParams params = scaled(params_in);
  params.A = resolved_A(params_in);
  params.recall_target = 0;
  std::vector<float> storage;
  queries = to_structure(queries, n, storage);
  KnnResult out;
  reference_scaled(queries, n, params, out, examined, threads);
  distances_to_caller(out.dist2.data(), out.dist2.size());
  return out;
}

}  // namespace bhcl
