/* Exact radius search on the kd-tree of kdtree_knn.cl: one work-item per query, depth-first with
 * a fixed-size private stack, every cell whose lower bound is <= r2 visited (the bound is summed
 * as bhcl_dist2 sums, so a point within r is never pruned: see kdtree_knn.cl).
 *
 * BHCL_KD_STACK: stack entries, at least the tree's inner depth. */
#include "radius_common.h"
#include "kdtree_common.h"

#ifndef BHCL_KD_STACK
#define BHCL_KD_STACK 32
#endif

__kernel void kdtree_radius(__global const bhcl_kd_node* nodes, __global const float4* points,
                            BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  uint examined = 0;
  if (bhcl_query_is_finite(q)) {
    float4 st_off[BHCL_KD_STACK];
    uint st_node[BHCL_KD_STACK];
    int sp = 0;
    uint node = 0;
    float4 off = (float4)(0.0f);
    for (;;) {
      bhcl_kd_node nd = nodes[node];
      if (nd.dim != BHCL_KD_LEAF) {
        uint far_child;
        float4 far_off;
        uint near_child = bhcl_kd_descend(nd, node, q, off, &far_child, &far_off);
        if (far_off.w <= r2) {
          st_off[sp] = far_off;
          st_node[sp] = far_child;
          ++sp;
        }
        node = near_child;
        continue;
      }
      uint end = nd.a + nd.b;
      examined += nd.b;
      for (uint i = nd.a; i < end; ++i) {
        float4 p = points[i];
        float d = bhcl_dist2(q, p);
        if (d <= r2) bhcl_radius_emit(fill, out_ids, out_d2, base, limit, &found, d, as_int(p.w));
      }
      if (sp == 0) break;
      --sp;
      node = st_node[sp];
      off = st_off[sp];
    }
  }
  BHCL_RADIUS_END(examined);
}
