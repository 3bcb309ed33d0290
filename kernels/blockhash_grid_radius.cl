/* Block hashing, grid layout (the auto preset): radius search, one work-item per query, the
 * count and fill passes of radius_common.h. The traversal is grid_search.h's with the radius as
 * the bound: every cell whose slabs come within r is scanned, so with no budget (0) the answer is
 * exact; a budget stops after that many points examined, and the slice is then a subset. */
#include "radius_common.h"

inline void ge_scan(bhcl_radius_slice* e, float qx, float qy, float qz, __global const float* px,
                    __global const float* py, __global const float* pz, __global const int* pid,
                    uint a, uint b) {
  for (uint p = a; p < b; ++p) {
    float d = bhcl_dist2_xyz(qx, qy, qz, px[p], py[p], pz[p]);
    if (d <= e->r2) bhcl_slice_emit(e, d, pid[p]);
  }
}

#define BHCL_GRID_STATE bhcl_radius_slice
#define BHCL_GRID_BOUND(st) ((st)->r2)
#define BHCL_GRID_SCAN(st, a, b) ge_scan(st, qx, qy, qz, px, py, pz, pid, a, b)
#define BHCL_GRID_ROWBUF 1 /* runs scanned as met (cap 0): every run within r is scanned anyway */
/* The level-2 box read per child, not kept (one program for every device, and on sm_90 keeping it
 * cost 68 registers against 63; on a CPU the box is a cached 24-byte load). */
#define BHCL_GRID_KEEP_BOX2 0
#include "grid_search.h"

__kernel void blockhash_grid_radius(__global const uint* starts, __global const float* px,
                                    __global const float* py, __global const float* pz,
                                    __global const int* pid, __global const uchar* occ, float4 geo0, float4 geo1, uint4 dims,
                                    float4 box_lo, float4 box_hi,
                                    uint budget, BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  uint examined = 0;
  const bhcl_grid_geom g = bhcl_grid_geom_from(geo0, geo1, dims);
  const bhcl_grid_dbox db = bhcl_grid_dbox_from(box_lo, box_hi);
  if (bhcl_query_is_finite(q)) {
    const float qx = q.x, qy = q.y, qz = q.z;
    bhcl_radius_slice e = BHCL_RADIUS_SLICE;
    examined = bhcl_grid_search(starts, px, py, pz, pid, occ, g, db, qx, qy, qz, budget ? budget : 0xffffffffu, 0u,
                                BHCL_GRID_FINE_RINGS, 0u, 0u, &e);
    found = e.found;
  }
  BHCL_RADIUS_END(examined);
}
