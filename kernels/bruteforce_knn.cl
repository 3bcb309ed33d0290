/* Exact kNN by brute force: one work-item per query, the points streamed through local memory in
 * tiles of the work-group size. Removed points (updates) stay in the array until a compaction,
 * their ids marked in `removed`. */
#include "knn_common.h"

__kernel void bruteforce_knn(__global const float4* points, uint n_points, __global const uint* removed,
                             uint removed_words, BHCL_KNN_QUERY_PARAMS, BHCL_KNN_RESULT_PARAMS,
                             __local float4* tile) {
  /* A warm-up launch (count 0) compiles the kernel and returns before any barrier. */
  if (count == 0) return;
  uint gid = get_global_id(0);
  uint lid = get_local_id(0);
  uint lsz = get_local_size(0);
  int active = gid < count;
  ulong row = first + gid;
  float3 q = active ? bhcl_load_query(queries, row) : (float3)(0.0f);
  int search = active && bhcl_query_is_finite(q);

  float best_d[BHCL_KMAX];
  int best_i[BHCL_KMAX];
  bhcl_topk_init(best_d, best_i, k);
  uint nfound = 0;

  for (uint base = 0; base < n_points; base += lsz) {
    uint m = min(lsz, n_points - base);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid < m) {
      float4 p = points[base + lid];
      /* A removed point (its id marked) made NaN: no distance comparison accepts it. */
      if (bhcl_id_removed(removed, removed_words, as_uint(p.w))) p.x = NAN;
      tile[lid] = p;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (search) {
      for (uint j = 0; j < m; ++j) {
        float d = bhcl_dist2(q, tile[j]);
        int idx = as_int(tile[j].w);  /* the point's id (stable across updates) */
        if (d <= max_r2 && bhcl_topk_accepts(best_d, best_i, k, d, idx))
          nfound = bhcl_topk_push(best_d, best_i, k, nfound, d, idx);
      }
    }
  }
  if (active) bhcl_write_row(out_ids, out_d2, out_counts, bhcl_out_row(out_rows, remap, row), k, best_d, best_i);
}
