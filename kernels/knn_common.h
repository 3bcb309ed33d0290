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

/* Whether point id `id` was removed: bit id % 32 of removed[id / 32] (the index's marks, of the
 * first `words` words; an id past them is live). */
inline int bhcl_id_removed(__global const uint* removed, uint words, uint id) {
  return (id >> 5) < words && ((removed[id >> 5] >> (id & 31u)) & 1u);
}

/* The query parameters every kNN kernel takes, in the order the host's KernelArgs::add_queries
 * sets them (lib/src/core/device_util.hpp), and the result buffers (add_results). */
#define BHCL_KNN_QUERY_PARAMS \
  __global const float *queries, ulong first, uint count, uint k, float max_r2
/* out_rows (when remap): the output row of each dispatch row (the caller's row of a query sent in
 * Hilbert order), so that results land in the caller's order with no pass after the kernel. */
#define BHCL_KNN_RESULT_PARAMS \
  __global int *out_ids, __global float *out_d2, __global int *out_counts, __global const uint *out_rows, uint remap

/* The opening of a kernel with one work-item per query and no barriers: the work-item's `row` and
 * query `q`, and an empty top-k list (best_d, best_i, nfound). The warm-up launch (count 0) and the
 * surplus work-items of the last group return at once. */
#define BHCL_KNN_BEGIN                      \
  uint gid = get_global_id(0);              \
  if (gid >= count) return;                 \
  ulong row = first + gid;                  \
  float3 q = bhcl_load_query(queries, row); \
  float best_d[BHCL_KMAX];                  \
  int best_i[BHCL_KMAX];                    \
  bhcl_topk_init(best_d, best_i, k);        \
  uint nfound = 0

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

/* The output row of dispatch row `row` (BHCL_KNN_RESULT_PARAMS). */
inline ulong bhcl_out_row(__global const uint* out_rows, uint remap, ulong row) {
  return remap ? (ulong)out_rows[row] : row;
}

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
