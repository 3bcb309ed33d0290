/* Pieces every kNN kernel shares: the distance, the top-k list kept in private memory (registers
 * for small k), the query load and the result write. OpenCL C only.
 *
 * BHCL_KMAX (a -D define) is the compiled capacity of the list; the runtime k <= BHCL_KMAX. */
#ifndef BHCL_KNN_COMMON_H
#define BHCL_KNN_COMMON_H

#include "bhcl_shared.h"

#ifndef BHCL_KMAX
#define BHCL_KMAX 32
#endif

/* Bit-exact agreement with the host reference needs unfused multiply-adds. */
#pragma OPENCL FP_CONTRACT OFF

/* sum((q-p)^2), evaluated left to right as the host reference does. */
inline float bhcl_dist2(float3 q, float4 p) {
  float dx = q.x - p.x;
  float dy = q.y - p.y;
  float dz = q.z - p.z;
  return dx * dx + dy * dy + dz * dz;
}

/* Loads query row `row` of an n x 3 float array. */
inline float3 bhcl_load_query(__global const float* queries, ulong row) {
  return vload3((size_t)row, queries);
}

inline int bhcl_query_is_finite(float3 q) {
  return isfinite(q.x) && isfinite(q.y) && isfinite(q.z);
}

/* The top-k list: d[] ascending, ties by lower id; empty slots are (+inf, BHCL_EMPTY_SLOT_ID). */
inline void bhcl_topk_init(float* d, int* id, uint k) {
  for (uint j = 0; j < k; ++j) {
    d[j] = INFINITY;
    id[j] = BHCL_EMPTY_SLOT_ID;
  }
}

/* True when (dist, idx) ranks before the current k-th entry. */
inline int bhcl_topk_accepts(const float* d, const int* id, uint k, float dist, int idx) {
  float wd = d[k - 1];
  return dist < wd || (dist == wd && idx < id[k - 1]);
}

/* Inserts (dist, idx), which must be accepted, into a list that holds n entries (n <= k),
 * dropping the k-th entry of a full list. It starts at the first free slot while the list fills,
 * so the +inf tail is never shifted (at k = 50 the shifts cost ~30 % of a kernel). Returns the new
 * count. */
inline uint bhcl_topk_push(float* d, int* id, uint k, uint n, float dist, int idx) {
  uint j = n < k ? n : k - 1;
  while (j > 0 && (d[j - 1] > dist || (d[j - 1] == dist && id[j - 1] > idx))) {
    d[j] = d[j - 1];
    id[j] = id[j - 1];
    --j;
  }
  d[j] = dist;
  id[j] = idx;
  return n < k ? n + 1 : n;
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
