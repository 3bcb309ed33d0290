/* Exact radius search on the kd-tree of kdtree_knn.cl: one work-item per query, depth-first with
 * a fixed-size private stack, every cell whose lower bound is <= r2 visited (the bound is summed
 * as bhcl_dist2 sums, so a point within r is never pruned: see kdtree_knn.cl).
 *
 * BHCL_KD_STACK: stack entries, at least the tree's inner depth. */
#include "radius_common.h"

/* The query's slice and the points examined, as the traversal's state. */
typedef struct kd_emit {
  bhcl_radius_slice out;
  uint examined;
} kd_emit;

inline __attribute__((always_inline)) void kd_emit_scan(kd_emit* e, __global const float4* points,
                                                        float3 q, uint a, uint end) {
  e->examined += end - a;
  for (uint i = a; i < end; ++i) {
    float4 p = points[i];
    float d = bhcl_dist2(q, p);
    if (d <= e->out.r2) bhcl_slice_emit(&e->out, d, as_int(p.w));
  }
}

#define BHCL_KD_STATE kd_emit
#define BHCL_KD_BOUND(st) ((st)->out.r2)
#define BHCL_KD_SCAN(st, a, e) kd_emit_scan(st, points, q, a, e)
#include "kdtree_common.h"

__kernel void kdtree_radius(__global const bhcl_kd_node* nodes, __global const float4* points,
                            BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  uint examined = 0;
  if (bhcl_query_is_finite(q)) {
    kd_emit e = {BHCL_RADIUS_SLICE, 0u};
    bhcl_kd_search(nodes, points, q, &e);
    found = e.out.found;
    examined = e.examined;
  }
  BHCL_RADIUS_END(examined);
}
