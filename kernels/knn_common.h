/* Pieces every kNN kernel shares: the top-k list kept in private memory (registers for small k),
 * the query load and the result write. OpenCL C only; the arithmetic is in bhcl_arith.h.
 *
 * BHCL_KMAX (a -D define) is the compiled capacity of the list; the runtime k <= BHCL_KMAX. */
#ifndef BHCL_KNN_COMMON_H
#define BHCL_KNN_COMMON_H

#include "bhcl_arith.h"

#ifndef BHCL_KMAX
#define BHCL_KMAX 32
#endif

/* sum((q-p)^2) on vector types (bhcl_arith.h holds the arithmetic). */
inline float bhcl_dist2(float3 q, float4 p) { return bhcl_dist2_xyz(q.x, q.y, q.z, p.x, p.y, p.z); }

/* Loads query row `row` of an n x 3 float array. */
inline float3 bhcl_load_query(__global const float* queries, ulong row) {
  return vload3((size_t)row, queries);
}

inline int bhcl_query_is_finite(float3 q) {
  return isfinite(q.x) && isfinite(q.y) && isfinite(q.z);
}

/* The top-k list (bhcl_arith.h: accepts and push): empty slots are (+inf, BHCL_EMPTY_SLOT_ID). */
inline void bhcl_topk_init(float* d, int* id, uint k) {
  for (uint j = 0; j < k; ++j) {
    d[j] = INFINITY;
    id[j] = BHCL_EMPTY_SLOT_ID;
  }
}

/* The squared distance a candidate must beat: the k-th entry's. */
inline float bhcl_topk_bound(const float* d, uint k) { return d[k - 1]; }

/* Writes row `row` of the results under the contract: -1/+inf for empty slots, and the count. */
inline void bhcl_write_row(__global int* out_ids, __global float* out_d2, __global int* out_counts,
                           ulong row, uint k, const float* d, const int* id) {
  size_t base = (size_t)row * (size_t)k;
  int count = 0;
  for (uint j = 0; j < k; ++j) {
    int empty = id[j] == BHCL_EMPTY_SLOT_ID;
    out_ids[base + j] = empty ? BHCL_MISSING_ID : id[j];
    out_d2[base + j] = empty ? INFINITY : d[j];
    count += empty ? 0 : 1;
  }
  out_counts[row] = count;
}

#endif /* BHCL_KNN_COMMON_H */
