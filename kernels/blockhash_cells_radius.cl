/* Block hashing, cell-aligned layout (blockhash_cells_knn.cl's structure): approximate radius
 * search, one work-item per query.
 *
 * The cells the probes reach (home; the octant with probes >= 1; the 4 x 4 x 4 block with probes
 * 2) whose slab distance is within r, nearest first (stable: home first); in each, the blocks of
 * its run whose box is within r are scanned, until `budget` points are examined (0: no budget).
 * Every point found is within r, so the answer is a subset of the exact one: points in cells the
 * probes do not reach, or past the budget, are missed (the recall is measured, docs/ACCURACY.md).
 * Runs never overlap (a block belongs to one cell), so no point is found twice. */
#include "radius_common.h"
#include "blockhash_layout.h"
#include "blockhash_common.h"

__kernel void blockhash_cells_radius(BHCL_BH_CELLS_PARAMS, uint budget, BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  uint examined = 0;
  if (bhcl_query_is_finite(q)) {
    bh_axes ax;
    bh_query_axes(thresholds, P, q, probes, &ax);
    const uint span = probes == 0 ? 1u : (probes == 1 ? 2u : (uint)BHCL_BH_AXIS_CELLS);
    float ccd[BHCL_BH_MAXCELLS];
    uint cid[BHCL_BH_MAXCELLS];
    uint ncell = 0;
    for (uint a = 0; a < span; ++a)
      for (uint b = 0; b < span; ++b)
        for (uint c = 0; c < span; ++c) {
          float cd = bh_slot_dist(&ax, a, b, c);
          if (!(cd <= r2)) continue;
          ncell = bh_insert_by_distance(ccd, cid, ncell, cd, (a << 4) | (b << 2) | c);
        }
    int stop = 0;
    for (uint i = 0; i < ncell && !stop; ++i) {
      uint rf, rn;
      if (BH_SLOT_RUN(&ax, cid[i], &rf, &rn) < 0) continue;
      for (uint r = 0; r < rn; ++r) {
        if (budget && examined >= budget) {
          stop = 1;
          break;
        }
        __global const bhcl_bh_box* box = boxes + rf + r;
        if (bh_box_dist2(q, box) > r2) continue;
        examined += bh_radius_scan_block(q, blocks + rf + r, box->count, r2, fill, out_ids, out_d2, base, limit,
                                         &found);
      }
    }
  }
  BHCL_RADIUS_END(examined);
}
