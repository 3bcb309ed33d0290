/* Block hashing (Ma & McCool 2002): approximate kNN, one work-item per query.
 *
 * Per query: hash the query in each of the L tables (P thresholds per dimension, binary search);
 * take the bucket of its cell (and, with probes, of the adjacent cell on the near side along each
 * axis); order the non-empty buckets by |Q| (stable: table, then home/x/y/z); scan their blocks in
 * that order, each block once, until ceil(A k) points have been examined; keep the k nearest in
 * private memory. With BHCL_BH_BOXSKIP a block whose bounding box is farther than the current k-th
 * distance (or the maximum radius) is skipped without counting: nothing in it can enter the list.
 * lib/src/blockhash/query_ref.cpp is the host reference of exactly this algorithm: change both.
 *
 * Defines: BHCL_KMAX (top-k capacity), BHCL_BH_L (tables), BHCL_BH_DIRECT (1: all (P+1)^3 cells
 * addressed directly; 0: binary search in the sorted directory of occupied cells),
 * BHCL_BH_BOXSKIP, BHCL_BH_SCANCAP (most blocks scanned per query; X needs no define: each box
 * holds its block's point count),
 * BHCL_BH_BOXORDER (1: scan the gathered blocks in order of box distance with an early stop, the
 * CPU form of docs/DESIGN.md; 0: in bucket order, the talk's), BHCL_BH_MAXKEEP (box order: the most
 * blocks a query keeps and scans; = BHCL_BH_SCANCAP). */
#include "knn_common.h"
#include "blockhash_layout.h"
#include "blockhash_common.h"

#ifndef BHCL_BH_DIRECT
#define BHCL_BH_DIRECT 0
#endif
#ifndef BHCL_BH_BOXSKIP
#define BHCL_BH_BOXSKIP 1
#endif
#ifndef BHCL_BH_SCANCAP
#define BHCL_BH_SCANCAP 128
#endif
#ifndef BHCL_BH_BOXORDER
#define BHCL_BH_BOXORDER 0
#endif
#ifndef BHCL_BH_MAXKEEP
#define BHCL_BH_MAXKEEP 128
#endif

/* Offers candidate block b at box distance d to the list of the `keep` nearest distinct blocks
 * (n held), ranked and inserted as the top-k list is: (box distance, block). Returns the new n. A
 * block already held has the same d: skipped. */
inline uint bh_keep(float* cd, int* cb, uint n, uint keep, float d, int b, float max_r2) {
  if (d > max_r2) return n;
  if (n == keep && !bhcl_topk_accepts(cd, cb, keep, d, b)) return n;
  for (uint i = 0; i < n; ++i)
    if (cb[i] == b) return n;
  return bhcl_topk_push(cd, cb, keep, n, d, b);
}

/* The query's Hilbert key: quantised with the build's origin (xyz) and scale (w), in float. */
inline ulong bh_query_key(float3 q, float4 qq, uint bits) {
  float top = (float)((1u << bits) - 1);
  float v0 = floor((q.x - qq.x) * qq.w), v1 = floor((q.y - qq.y) * qq.w), v2 = floor((q.z - qq.z) * qq.w);
  v0 = v0 > 0.0f ? v0 : 0.0f;
  v1 = v1 > 0.0f ? v1 : 0.0f;
  v2 = v2 > 0.0f ? v2 : 0.0f;
  v0 = v0 > top ? top : v0;
  v1 = v1 > top ? top : v1;
  v2 = v2 > top ? top : v2;
  return bh_hilbert_encode((uint)v0, (uint)v1, (uint)v2, bits);
}

__kernel void blockhash_knn(BHCL_BH_TABLE_PARAMS, __global const ulong* block_keys, uint n_blocks,
                            float4 qquant, uint qbits, uint seeds, BHCL_BH_KNN_PARAMS) {
  BHCL_KNN_BEGIN;
  uint examined = 0;

  if (bhcl_query_is_finite(q)) {
    /* 1. Buckets, sorted by |Q| with a stable insertion. */
    bh_buckets cand;
    BH_QUERY_BUCKETS(q, &cand);

#if BHCL_BH_BOXORDER
    /* 2. Box order (the CPU form of docs/DESIGN.md): of the blocks of those buckets (and the Hilbert
     * seeds), the `keep` nearest distinct by (box distance, block), kept sorted while gathering;
     * scanned in that order until the budget is spent or the next box is farther than the k-th
     * distance. keep = ceil(budget / X) + 1 blocks always spend the budget (every block but the
     * last holds X points), so the bounded list scans what a full sort would. */
    float cd[BHCL_BH_MAXKEEP];
    int cb[BHCL_BH_MAXKEEP];
    uint nc = 0;
    if (seeds > 0) {
      /* The blocks around the query's own Hilbert position. */
      ulong key = bh_query_key(q, qquant, qbits);
      int j = (int)bh_block_at_key(block_keys, n_blocks, key);
      int a = max(0, j - (int)seeds), e = min((int)n_blocks - 1, j + (int)seeds);
      for (int b = a; b <= e; ++b) nc = bh_keep(cd, cb, nc, keep, bh_box_dist2(q, boxes + b), b, max_r2);
    }
    for (uint s = 0; s < cand.n; ++s) {
      bhcl_bh_bucket bk = buckets[cand.b[s]];
      for (uint r = 0; r < bk.n_refs; ++r) {
        int b = refs[bk.first_ref + r];
        nc = bh_keep(cd, cb, nc, keep, bh_box_dist2(q, boxes + b), b, max_r2);
      }
    }
    for (uint i = 0; i < nc; ++i) {
      if (examined >= budget || cd[i] > bhcl_topk_bound(best_d, k)) break;
      int b = cb[i];
      examined += bh_scan_block(q, blocks + b, boxes[b].count, max_r2, best_d, best_i, k, &nfound);
    }
#else
    /* 2. Priority order (the talk's): the blocks of the buckets in bucket order, each scanned once,
     * until the budget is spent. A 128-bit filter over the scanned blocks spares most of the
     * linear duplicate searches. */
    int scanned[BHCL_BH_SCANCAP];
    uint nscanned = 0;
    ulong seen0 = 0, seen1 = 0;
    for (uint s = 0; s < cand.n; ++s) {
      bhcl_bh_bucket bk = buckets[cand.b[s]];
      int done = 0;
      for (uint r = 0; r < bk.n_refs; ++r) {
        if (examined >= budget || nscanned >= BHCL_BH_SCANCAP) {
          done = 1;
          break;
        }
        int b = refs[bk.first_ref + r];
        __global const bhcl_bh_box* box = boxes + b;
#if BHCL_BH_BOXSKIP
        float bd = bh_box_dist2(q, box);
        if (bd > max_r2 || bd > bhcl_topk_bound(best_d, k)) continue;
#endif
        uint hb = ((uint)b * 0x9E3779B1u) >> 25;
        ulong bit = (ulong)1 << (hb & 63);
        int maybe = (hb & 64) ? (seen1 & bit) != 0 : (seen0 & bit) != 0;
        if (maybe) {
          int dup = 0;
          for (uint u = 0; u < nscanned; ++u) dup |= scanned[u] == b;
          if (dup) continue;
        }
        if (hb & 64) seen1 |= bit;
        else seen0 |= bit;
        scanned[nscanned++] = b;
        examined += bh_scan_block(q, blocks + b, box->count, max_r2, best_d, best_i, k, &nfound);
      }
      if (done) break;
    }
#endif
  }
  BHCL_BH_KNN_END(examined);
}
