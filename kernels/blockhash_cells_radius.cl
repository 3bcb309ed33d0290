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

#define BHCL_BH_MAXCELLS (BHCL_BH_AXIS_CELLS * BHCL_BH_AXIS_CELLS * BHCL_BH_AXIS_CELLS)

__kernel void blockhash_cells_radius(__global const bhcl_bh_block* blocks,
                                     __global const bhcl_bh_box* boxes,
                                     __global const float* thresholds, uint P,
                                     __global const uint* keys, uint n_keys,
                                     __global const bhcl_bh_bucket* buckets,
                                     __global const uint2* direct, uint dir_dy, uint dir_dz,
                                     uint probes, uint budget, BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  uint examined = 0;
  if (bhcl_query_is_finite(q)) {
    uint cx[BHCL_BH_AXIS_CELLS], cy[BHCL_BH_AXIS_CELLS], cz[BHCL_BH_AXIS_CELLS];
    float dx[BHCL_BH_AXIS_CELLS], dy[BHCL_BH_AXIS_CELLS], dz[BHCL_BH_AXIS_CELLS];
    bh_axis_cells(thresholds, P, q.x, probes, cx, dx);
    bh_axis_cells(thresholds + P, P, q.y, probes, cy, dy);
    bh_axis_cells(thresholds + 2 * P, P, q.z, probes, cz, dz);
    const uint side = P + 1;
    const uint span = probes == 0 ? 1u : (probes == 1 ? 2u : (uint)BHCL_BH_AXIS_CELLS);
    float ccd[BHCL_BH_MAXCELLS];
    uint cid[BHCL_BH_MAXCELLS];
    uint ncell = 0;
    for (uint a = 0; a < span; ++a)
      for (uint b = 0; b < span; ++b)
        for (uint c = 0; c < span; ++c) {
          float cd = (dx[a] + dy[b]) + dz[c];
          if (!(cd <= r2)) continue;
          ncell = bh_insert_by_distance(ccd, cid, ncell, cd, (a << 4) | (b << 2) | c);
        }
    int stop = 0;
    for (uint i = 0; i < ncell && !stop; ++i) {
      uint sa = cid[i] >> 4, sb = (cid[i] >> 2) & 3u, sc = cid[i] & 3u, rf, rn;
      if (bh_cell_run(direct, dir_dy, dir_dz, keys, n_keys, buckets, side, cx[sa], cy[sb],
                             cz[sc], &rf, &rn) < 0)
        continue;
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
