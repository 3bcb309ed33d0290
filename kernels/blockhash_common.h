/* Block hashing: what the L-table kernels share (blockhash_knn.cl, blockhash_radius.cl) beyond the arithmetic of bhcl_arith.h, which the host reference (lib/src/blockhash/query_ref.cpp)
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

/* The kNN kernels' closing parameters (after each layout's own) and their close: the row and
 * the points examined (when want_examined). */
#define BHCL_BH_KNN_PARAMS                                                               \
  BHCL_KNN_QUERY_PARAMS, uint budget, uint keep, BHCL_KNN_RESULT_PARAMS,                 \
      __global int *out_examined, uint want_examined
#define BHCL_BH_KNN_END(examined)                                      \
  ulong orow = bhcl_out_row(out_rows, remap, row);                     \
  bhcl_write_row(out_ids, out_d2, out_counts, orow, k, best_d, best_i); \
  if (want_examined) out_examined[orow] = (int)(examined)

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

/* The L-table layout's candidate buckets of a query: in each of the L tables the bucket of the
 * query's cell and, with probes, of its near-side neighbour along each axis; empty and absent
 * buckets skipped; sorted by |Q| with a stable insertion (ties keep table, then probe, order).
 * cand_q/cand_b hold at least 4 L entries. Returns how many were found. */
inline uint bh_gather_buckets(float3 q, int L, __global const float* thresholds, uint P,
                              __global const uint* keys, __global const uint* table_starts,
                              __global const bhcl_bh_bucket* buckets, uint probes, uint* cand_q,
                              uint* cand_b) {
  uint ncand = 0;
  const uint side = P + 1;
  for (int t = 0; t < L; ++t) {
    __global const float* thr = thresholds + (size_t)t * 3 * P;
    uint h0 = bh_hash(thr, P, q.x), h1 = bh_hash(thr + P, P, q.y), h2 = bh_hash(thr + 2 * P, P, q.z);
    int n0 = -1, n1 = -1, n2 = -1;
    if (probes) {
      n0 = bh_near_side(thr, P, h0, q.x);
      n1 = bh_near_side(thr + P, P, h1, q.y);
      n2 = bh_near_side(thr + 2 * P, P, h2, q.z);
    }
    for (int pr = 0; pr < (probes ? 4 : 1); ++pr) {
      uint c0 = h0, c1 = h1, c2 = h2;
      if (pr == 1) { if (n0 < 0) continue; c0 = (uint)n0; }
      if (pr == 2) { if (n1 < 0) continue; c1 = (uint)n1; }
      if (pr == 3) { if (n2 < 0) continue; c2 = (uint)n2; }
      long b = bh_find_bucket(keys, table_starts, P, t, (c0 * side + c1) * side + c2);
      if (b < 0) continue;
      bhcl_bh_bucket bk = buckets[b];
      if (bk.n_refs == 0) continue;
      uint aq = (uint)abs(bk.q);
      uint pos = ncand++;
      while (pos > 0 && cand_q[pos - 1] > aq) {
        cand_q[pos] = cand_q[pos - 1];
        cand_b[pos] = cand_b[pos - 1];
        --pos;
      }
      cand_q[pos] = aq;
      cand_b[pos] = (uint)b;
    }
  }
  return ncand;
}

/* The L-table layout's kernel parameters (blockhash_knn.cl, blockhash_radius.cl; the order
 * lib/src/blockhash/search.cpp sets them in), and a query's buckets in the order it visits them
 * (bh_gather_buckets: at most 4 L). */
#define BHCL_BH_TABLE_PARAMS                                                                      \
  __global const bhcl_bh_block *blocks, __global const bhcl_bh_box *boxes,                        \
      __global const float *thresholds, uint P, __global const uint *keys,                        \
      __global const uint *table_starts, __global const bhcl_bh_bucket *buckets,                  \
      __global const int *refs, uint probes

#ifndef BHCL_BH_L
#define BHCL_BH_L 4
#endif
#define BHCL_BH_MAXBUCKETS (4 * BHCL_BH_L)
typedef struct bh_buckets {
  uint q[BHCL_BH_MAXBUCKETS], b[BHCL_BH_MAXBUCKETS];
  uint n;
} bh_buckets;

#define BH_QUERY_BUCKETS(q, out)                                                              \
  ((out)->n = bh_gather_buckets(q, BHCL_BH_L, thresholds, P, keys, table_starts, buckets, probes, \
                                (out)->q, (out)->b))

#ifdef BHCL_RADIUS_COMMON_H
/* Radius kernels: every point of one block within r2 emitted (bhcl_radius_emit); returns the
 * block's point count (the examined measure). */
inline uint bh_radius_scan_block(float3 q, __global const bhcl_bh_block* blk, int cnt, float r2, uint fill,
                                 __global int* out_ids, __global float* out_d2, ulong base, uint limit,
                                 uint* found) {
  for (int j = 0; j < cnt; ++j) {
    float d = bhcl_dist2_xyz(q.x, q.y, q.z, blk->x[j], blk->y[j], blk->z[j]);
    if (d <= r2) bhcl_radius_emit(fill, out_ids, out_d2, base, limit, found, d, blk->id[j]);
  }
  return (uint)cnt;
}
#endif

#endif /* BHCL_BLOCKHASH_COMMON_H */
