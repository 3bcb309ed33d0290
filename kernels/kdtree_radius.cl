/* Exact radius search on the kd-tree of kdtree_knn.cl: one work-item per query, depth-first with
 * a fixed-size private stack, every cell whose lower bound is <= r2 visited (the bound is summed
 * as bhcl_dist2 sums, so a point within r is never pruned: see kdtree_knn.cl).
 *
 * BHCL_KD_STACK: stack entries, at least the tree's inner depth. */
#include "radius_common.h"
#include "kdtree_layout.h"

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
        float qd = nd.dim == 0u ? q.x : (nd.dim == 1u ? q.y : q.z);
        float diff = qd - nd.split;
        int go_left = diff < 0.0f;
        uint near_child = go_left ? node + 1u : nd.a;
        uint far_child = go_left ? nd.a : node + 1u;
        float4 far_off = off;
        if (nd.dim == 0u) far_off.x = diff;
        else if (nd.dim == 1u) far_off.y = diff;
        else far_off.z = diff;
        if (bhcl_dist2((float3)(0.0f), far_off) <= r2) {
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
