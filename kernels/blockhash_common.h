/* Block hashing: what the block-hash kernels share (blockhash_knn.cl, blockhash_cells_knn.cl, the
 * radius kernels)
 * beyond the arithmetic of bhcl_arith.h, which the host reference (lib/src/blockhash/query_ref.cpp)
 * includes too. OpenCL C. */
#ifndef BHCL_BLOCKHASH_COMMON_H
#define BHCL_BLOCKHASH_COMMON_H

#include "knn_common.h"
#include "blockhash_layout.h"

/* The box distance on vector types (bhcl_arith.h holds the arithmetic). */
inline float bh_box_dist2(float3 q, __global const bhcl_bh_box* b) {
  return bh_box_dist2_xyz(q.x, q.y, q.z, b);
}

/* Scans one block into the top-k list; returns its point count. */
inline uint bh_scan_block(float3 q, __global const bhcl_bh_block* blk, int cnt, float max_r2,
                          float* best_d, int* best_i, uint k, uint* nfound) {
  for (int j = 0; j < cnt; ++j) {
    float4 p = (float4)(blk->x[j], blk->y[j], blk->z[j], 0.0f);
    float d = bhcl_dist2(q, p);
    int id = blk->id[j];
    if (d <= max_r2 && bhcl_topk_accepts(best_d, best_i, k, d, id))
      *nfound = bhcl_topk_push(best_d, best_i, k, *nfound, d, id);
  }
  return (uint)cnt;
}

/* The block whose first Hilbert key is the last <= key (block 0 when none is): where a query's
 * key falls in the block order (keys ascending, one per block). */
inline uint bh_block_at_key(__global const ulong* block_keys, uint n_blocks, ulong key) {
  /* Halving a window [base, base + len) that always ends where the keys pass `key`. */
  uint base = 0, len = n_blocks;
  while (len > 0) {
    uint mid = len >> 1;  /* not `half`: a type in OpenCL C */
    int below = block_keys[base + mid] <= key;
    base = below ? base + mid + 1 : base;
    len = below ? len - mid - 1 : mid;
  }
  return base > 0 ? base - 1 : 0;
}

/* The run of a table-0 cell: from the direct table when there is one (one load: cells are
 * numbered densely over the thresholds each axis actually has), else by binary search in the sorted
 * directory. Returns 0 and sets *first, *n, or -1 for an empty cell. */
inline int bh_cell_run(__global const uint2* direct, uint dy, uint dz, __global const uint* keys,
                       uint n_keys, __global const bhcl_bh_bucket* buckets, uint side, uint cx,
                       uint cy, uint cz, uint* first, uint* n) {
  if (dz) {
    uint2 e = direct[(cx * dy + cy) * dz + cz];
    *first = e.x;
    *n = e.y;
    return e.y ? 0 : -1;
  }
  uint key = (cx * side + cy) * side + cz;
  uint lo = 0, hi = n_keys;
  while (lo < hi) {
    uint mid = (lo + hi) >> 1;
    if (keys[mid] < key) lo = mid + 1;
    else hi = mid;
  }
  if (lo >= n_keys || keys[lo] != key) return -1;
  *first = buckets[lo].first_ref;
  *n = buckets[lo].n_refs;
  return 0;
}

/* The L-table layout: the bucket of a cell in a table, or -1 (BHCL_BH_DIRECT: all (P+1)^3 cells
 * of a table addressed directly). */
#ifndef BHCL_BH_DIRECT
#define BHCL_BH_DIRECT 0
#endif
inline long bh_find_bucket(__global const uint* keys, __global const uint* table_starts, uint P,
                           int table, uint key) {
#if BHCL_BH_DIRECT
  ulong side = (ulong)P + 1;
  return (long)((ulong)table * side * side * side + key);
#else
  uint lo = table_starts[table], hi = table_starts[table + 1];
  while (lo < hi) {
    uint mid = (lo + hi) >> 1;
    if (keys[mid] < key) lo = mid + 1;
    else hi = mid;
  }
  return (lo < table_starts[table + 1] && keys[lo] == key) ? (long)lo : -1;
#endif
}

#endif /* BHCL_BLOCKHASH_COMMON_H */
