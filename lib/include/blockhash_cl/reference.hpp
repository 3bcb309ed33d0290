// Host references of the query algorithms: plain C++ that the kernels are tested against.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl::reference {

// Exact kNN with the kernels' arithmetic: float, sum((q-p)^2) evaluated as dx*dx + dy*dy + dz*dz
// left to right, no fused multiply-add. The brute-force kernel equals it bit for bit.
// Threads: 0 uses all hardware threads.
KnnResult knn_float(const float* points, std::size_t n_points, const float* queries,
                    std::size_t n_queries, const SearchParams& params, unsigned threads = 0);

// Exact kNN ranked by squared distances computed in double precision from the float inputs.
// dist2 holds the double distances rounded to float. The independent check of every method.
KnnResult knn_double(const float* points, std::size_t n_points, const float* queries,
                     std::size_t n_queries, const SearchParams& params, unsigned threads = 0);

// The kernels' ranking (knn_common.h) on the host: (d, i) ranks before (d2, i2) when nearer,
// ties to the lower index.
inline bool ranks_before(float d, std::int32_t i, float d2, std::int32_t i2) {
  return d < d2 || (d == d2 && i < i2);
}

// The kernels' top-k insertion on the host: d/id hold a list sorted by ranks_before; (dist, idx)
// goes into slot `last` (the k-th slot of a full list, or the first free one) and moves up to its
// place, shifting the entries it passes down by one.
inline void topk_insert_at(float* d, std::int32_t* id, std::size_t last, float dist, std::int32_t idx) {
  std::size_t j = last;
  while (j > 0 && ranks_before(dist, idx, d[j - 1], id[j - 1])) {
    d[j] = d[j - 1];
    id[j] = id[j - 1];
    --j;
  }
  d[j] = dist;
  id[j] = idx;
}

// Squared distance in double precision between point i and a query.
double dist2_double(const float* points, std::size_t i, const float* query);

// Squared distance exactly as the kernels compute it.
float dist2_float(const float* p, const float* q);

}  // namespace bhcl::reference
