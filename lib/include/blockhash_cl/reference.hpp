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

// Squared distance in double precision between point i and a query.
double dist2_double(const float* points, std::size_t i, const float* query);

// Squared distance exactly as the kernels compute it (bhcl_dist2_xyz of kernels/bhcl_arith.h).
float dist2_float(const float* p, const float* q);

}  // namespace bhcl::reference
