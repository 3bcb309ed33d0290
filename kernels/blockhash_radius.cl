/* Block hashing, L-table layout (blockhash_knn.cl's structure: the `paper` presets and auto
 * with grid=0): approximate radius search, one work-item per query.
 *
 * The buckets of the query's cell in each of the L tables (and, with probes, of the near-side
 * neighbour along each axis), ordered by |Q| as the kNN kernel orders them; their blocks in that
 * order, each at most once (the tables share blocks), those whose box is within r scanned until
 * `budget` points are examined (0: no budget) or BHCL_BH_SCANCAP blocks are scanned. Every point
 * found is within r: the answer is a subset of the exact one.
 *
 * Defines: BHCL_BH_L (tables), BHCL_BH_DIRECT, BHCL_BH_SCANCAP (most blocks scanned per query). */
#include "radius_common.h"
#include "blockhash_layout.h"
#include "blockhash_common.h"

#ifndef BHCL_BH_SCANCAP
#define BHCL_BH_SCANCAP 128
#endif

__kernel void blockhash_radius(BHCL_BH_TABLE_PARAMS, uint budget, BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  uint examined = 0;
  if (bhcl_query_is_finite(q)) {
    bh_buckets cand;
    BH_QUERY_BUCKETS(q, &cand);
    int scanned[BHCL_BH_SCANCAP];
    uint nscanned = 0;
    int stop = 0;
    for (uint s = 0; s < cand.n && !stop; ++s) {
      bhcl_bh_bucket bk = buckets[cand.b[s]];
      for (uint r = 0; r < bk.n_refs; ++r) {
        if ((budget && examined >= budget) || nscanned >= BHCL_BH_SCANCAP) {
          stop = 1;
          break;
        }
        int b = refs[bk.first_ref + r];
        __global const bhcl_bh_box* box = boxes + b;
        if (bh_box_dist2(q, box) > r2) continue;
        int dup = 0;
        for (uint u = 0; u < nscanned; ++u) dup |= scanned[u] == b;
        if (dup) continue;
        scanned[nscanned++] = b;
        examined += bh_radius_scan_block(q, blocks + b, box->count, r2, fill, out_ids, out_d2, base, limit, &found);
      }
    }
  }
  BHCL_RADIUS_END(examined);
}
