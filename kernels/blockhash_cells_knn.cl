/* Block hashing with cell-aligned blocks (the auto preset's layout): approximate kNN, one
 * work-item per query.
 *
 * The build orders the points by the Hilbert order of their cell in the primary table (then by
 * their own Hilbert key) and cuts blocks that never cross a cell, so the bucket of a cell is a run
 * of blocks holding exactly its points: first_ref is the run's first block, n_refs its length, and
 * no reference array is read. Per query, in three phases: (0) the cell of the query, which sets
 * a first k-th distance; (1) its near-side neighbours (the rest of the octant); (2) with probes 2,
 * and only while the k-th distance still reaches past the octant, the rest of the 4 x 4 x 4 block
 * (two near-side cells and the far one per axis). In each phase the cells within the bound (slab distances from the thresholds, no
 * memory) give their blocks; the `keep` nearest by box distance are scanned nearest first until
 * the next box is farther than the k-th distance or ceil(A k) points are examined.
 * A query whose cells hold fewer than k points (off the data, or k above the cells' population)
 * then scans the blocks around its cell's position in the block order (a window of 2 `seeds` + 1
 * blocks), so that every row is full whenever N >= k and the radius allows.
 * lib/src/blockhash/query_ref.cpp (reference_query_cells) is the host reference of exactly this
 * algorithm: change both.
 *
 * Defines: BHCL_KMAX (top-k capacity), BHCL_BH_MAXKEEP (the most blocks one phase keeps; the
 * runtime `keep` <= it), BHCL_BH_VECSCAN (1: a block's 16 distances as one float16 and a lane
 * mask, for CPU devices whose compilers vectorise it; 0: scalar, the GPU form; both give
 * identical results). */
#include "knn_common.h"
#include "blockhash_layout.h"
#include "blockhash_common.h"

#ifndef BHCL_BH_VECSCAN
#define BHCL_BH_VECSCAN 0
#endif
/* 1: the home cell is a phase of its own (a first k-th distance before the neighbours are
 * gathered); 0: the whole octant is gathered at once (an exploration switch: the host reference
 * follows 1). */
#ifndef BHCL_BH_HOMEFIRST
#define BHCL_BH_HOMEFIRST 1
#endif
#ifndef BHCL_BH_MAXKEEP
#define BHCL_BH_MAXKEEP 64
#endif


/* Scans one block into the top-k list (n entries held); returns its point count. */
inline uint bh_cells_scan(float3 q, __global const bhcl_bh_block* blk, int cnt, float max_r2,
                          float* best_d, int* best_i, uint k, uint* nfound) {
#if BHCL_BH_VECSCAN
  float16 dx = (float16)(q.x) - vload16(0, blk->x);
  float16 dy = (float16)(q.y) - vload16(0, blk->y);
  float16 dz = (float16)(q.z) - vload16(0, blk->z);
  float16 d16 = dx * dx + dy * dy + dz * dz;
  float bound = fmin(max_r2, bhcl_topk_bound(best_d, k));
  /* The lanes within the bound as a bit mask (unused slots are NaN: never within), then only
   * those lanes are visited, nearest-first order not needed: each is offered to the list in slot
   * order, as the scalar loop does. */
  int16 w = (d16 <= (float16)(bound)) &
            (int16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, 16384, 32768);
  int8 w8 = w.lo | w.hi;
  int4 w4 = w8.lo | w8.hi;
  int2 w2 = w4.lo | w4.hi;
  uint mask = (uint)(w2.x | w2.y);
  if (mask == 0u) return (uint)cnt;
  float dd[16];
  vstore16(d16, 0, dd);
  while (mask) {
    int j = 31 - (int)clz(mask & (0u - mask)); /* lowest set lane */
    mask &= mask - 1u;
    float d = dd[j];
    if (d > bound) continue; /* the bound tightened since the mask was taken */
    int id = blk->id[j];
    if (bhcl_topk_accepts(best_d, best_i, k, d, id)) {
      *nfound = bhcl_topk_push(best_d, best_i, k, *nfound, d, id);
      bound = fmin(max_r2, bhcl_topk_bound(best_d, k));
    }
  }
#else
  bh_scan_block(q, blk, cnt, max_r2, best_d, best_i, k, nfound);
#endif
  return (uint)cnt;
}

__kernel void blockhash_cells_knn(BHCL_BH_CELLS_PARAMS, __global const ulong* block_keys,
                                  uint n_blocks, uint cell_bits, uint seeds, BHCL_BH_KNN_PARAMS) {
  BHCL_KNN_BEGIN;
  uint examined = 0;

  if (bhcl_query_is_finite(q)) {
    bh_axes ax;
    bh_query_axes(thresholds, P, q, probes, &ax);
    uint run_first[BHCL_BH_MAXCELLS], run_end[BHCL_BH_MAXCELLS]; /* the runs entered, in order */
    uint nruns = 0;
    int stop = 0;
    /* Phase 1: the octant (home and near-side cells), sorted by slab distance (stable: home
     * first). Phase 2 (probes 2), only when the k-th distance still reaches past the octant: the
     * other cells of the 4 x 4 x 4 block within the k-th distance, sorted the same way. Each
     * visit stops at the first cell farther than the k-th distance. */
    for (int phase = BHCL_BH_HOMEFIRST ? 0 : 1; phase <= 2 && !stop; ++phase) {
      float ccd[BHCL_BH_MAXCELLS];
      uint cid[BHCL_BH_MAXCELLS];
      uint ncell = 0;
      uint span = phase == 0 ? 1 : (phase == 1 ? 2 : BHCL_BH_AXIS_CELLS);
      float bound0 = fmin(max_r2, bhcl_topk_bound(best_d, k));
      if (phase == 1 && probes < 1) break;
      if (phase == 2) {
        if (probes < 2) break;
        float nearest =
            fmin(fmin(fmin(ax.dx[2], ax.dx[3]), fmin(ax.dy[2], ax.dy[3])), fmin(ax.dz[2], ax.dz[3]));
        if (!(nearest <= bound0)) break;
      }
      for (uint a = 0; a < span; ++a)
        for (uint b = 0; b < span; ++b)
          for (uint c = 0; c < span; ++c) {
            if (BHCL_BH_HOMEFIRST && phase == 1 && a == 0 && b == 0 && c == 0) continue;
            if (phase == 2 && a < 2 && b < 2 && c < 2) continue;
            float cd = bh_slot_dist(&ax, a, b, c);
            if (!(cd < INFINITY) || cd > bound0) continue;
            /* axis slots, not the key: no divisions later */
            ncell = bh_insert_by_distance(ccd, cid, ncell, cd, (a << 4) | (b << 2) | c);
          }
      /* Gather: the blocks of those cells whose boxes are within the bound, the `keep` nearest by
       * (box distance, block) kept sorted (at most 4 keep box tests per cell: a cell of a heap of
       * duplicates cannot stall a query). keep = ceil(budget / X) + 1 blocks spend any budget, so
       * the bounded list scans what a full sort would. */
      float od[BHCL_BH_MAXKEEP];
      int ob[BHCL_BH_MAXKEEP];
      uint no = 0;
      for (uint i = 0; i < ncell; ++i) {
        if (ccd[i] > bound0) break;
        uint rf, rn;
        if (BH_SLOT_RUN(&ax, cid[i], &rf, &rn) < 0) continue;
        run_first[nruns] = rf;
        run_end[nruns] = rf + rn;
        ++nruns;
        uint rt = min(rn, 4u * keep);
        for (uint r = 0; r < rt; ++r) {
          int blk = (int)(rf + r);
          float bd = bh_box_dist2(q, boxes + blk);
          if (bd > bound0) continue;
          /* The same ranking and insertion as the top-k list: (box distance, block). */
          if (no == keep && !bhcl_topk_accepts(od, ob, keep, bd, blk)) continue;
          no = bhcl_topk_push(od, ob, keep, no, bd, blk);
        }
      }
      /* Scan nearest first until the budget is spent or a box is farther than the k-th distance. */
      for (uint j = 0; j < no; ++j) {
        if (od[j] > bhcl_topk_bound(best_d, k)) break;
        if (examined >= budget) {
          stop = 1;
          break;
        }
        int blk = ob[j];
        examined += bh_cells_scan(q, blocks + blk, boxes[blk].count, max_r2, best_d, best_i, k,
                                  &nfound);
      }
    }
    if (nfound < k && seeds > 0) {
      /* Fallback: the blocks around the home cell's position in the block order, except those of
       * the runs already entered. */
      ulong key = bh_hilbert_encode(ax.cx[0], ax.cy[0], ax.cz[0], cell_bits);
      long j = (long)bh_block_at_key(block_keys, n_blocks, key);
      long wa = j - (long)seeds, we = j + (long)seeds;
      if (wa < 0) {
        we -= wa;
        wa = 0;
      }
      if (we > (long)n_blocks - 1) {
        wa -= we - ((long)n_blocks - 1);
        we = (long)n_blocks - 1;
        if (wa < 0) wa = 0;
      }
      for (long b = wa; b <= we; ++b) {
        float bd = bh_box_dist2(q, boxes + b);
        if (bd > max_r2 || bd > bhcl_topk_bound(best_d, k)) continue;
        int dup = 0;
        for (uint u = 0; u < nruns; ++u) dup |= (ulong)b >= run_first[u] && (ulong)b < run_end[u];
        if (dup) continue;
        examined += bh_cells_scan(q, blocks + b, boxes[b].count, max_r2, best_d, best_i, k,
                                  &nfound);
      }
    }
  }
  BHCL_BH_KNN_END(examined);
}
