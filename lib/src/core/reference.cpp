// Host references. Both rank candidates by (distance, index), ties to the lower index, and honour
// max_radius and non-finite queries exactly as the kernels do.
#include "blockhash_cl/reference.hpp"

#include "core/parallel.hpp"

#include <algorithm>
#include <cmath>
#include <thread>

#include "bhcl_arith.h"
#include "blockhash_cl/error.hpp"

namespace bhcl::reference {
namespace {

template <typename D, typename DistFn>
KnnResult knn_generic(const float* points, std::size_t n_points, const float* queries,
                      std::size_t n_queries, const SearchParams& params, unsigned threads,
                      DistFn dist) {
  kmax_variant(params.k);  // validates k
  const int k = params.k;
  const D r2 = std::isinf(params.max_radius) ? D(INFINITY) : D(params.max_radius) * D(params.max_radius);
  KnnResult out;
  out.resize(n_queries, k);
  if (threads == 0) threads = detail::available_cpus();
  auto work = [&](std::size_t begin, std::size_t end) {
    std::vector<std::pair<D, std::int32_t>> best;
    best.reserve(k + 1);
    for (std::size_t qi = begin; qi < end; ++qi) {
      const float* q = queries + 3 * qi;
      if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) continue;
      best.clear();
      for (std::size_t i = 0; i < n_points; ++i) {
        D d = dist(points + 3 * i, q);
        if (!(d <= r2)) continue;
        std::pair<D, std::int32_t> c(d, static_cast<std::int32_t>(i));
        if (static_cast<int>(best.size()) == k && !(c < best.back())) continue;
        best.insert(std::upper_bound(best.begin(), best.end(), c), c);
        if (static_cast<int>(best.size()) > k) best.pop_back();
      }
      std::size_t row = qi * static_cast<std::size_t>(k);
      for (std::size_t j = 0; j < best.size(); ++j) {
        out.ids[row + j] = best[j].second;
        out.dist2[row + j] = static_cast<float>(best[j].first);
      }
      out.counts[qi] = static_cast<std::int32_t>(best.size());
    }
  };
  detail::parallel_for(n_queries, work, threads, 1);  // a throw reaches the caller
  return out;
}

}  // namespace

float dist2_float(const float* p, const float* q) {
  return bhcl_dist2_xyz(q[0], q[1], q[2], p[0], p[1], p[2]);
}

double dist2_double(const float* points, std::size_t i, const float* q) {
  const float* p = points + 3 * i;
  double dx = double(q[0]) - double(p[0]);
  double dy = double(q[1]) - double(p[1]);
  double dz = double(q[2]) - double(p[2]);
  return dx * dx + dy * dy + dz * dz;
}

KnnResult knn_float(const float* points, std::size_t n_points, const float* queries,
                    std::size_t n_queries, const SearchParams& params, unsigned threads) {
  return knn_generic<float>(points, n_points, queries, n_queries, params, threads,
                            [](const float* p, const float* q) { return dist2_float(p, q); });
}

KnnResult knn_double(const float* points, std::size_t n_points, const float* queries,
                     std::size_t n_queries, const SearchParams& params, unsigned threads) {
  return knn_generic<double>(points, n_points, queries, n_queries, params, threads,
                             [points](const float* p, const float* q) {
                               return dist2_double(points, (p - points) / 3, q);
                             });
}

}  // namespace bhcl::reference
