/* What the kd-tree kernels share (kdtree_knn.cl, kdtree_radius.cl): the descent step and the
 * traversal. OpenCL C.
 *
 * Before including this header the includer defines the search state (as for grid_search.h):
 *   BHCL_KD_STATE           the state's type (a top-k list, or a radius slice)
 *   BHCL_KD_BOUND(st)       float: the squared distance a cell or point must be within to matter
 *   BHCL_KD_SCAN(st, a, e)  scans a leaf's points [a, e) (points and q in scope)
 * BHCL_KD_STACK: stack entries, at least the tree's inner depth. */
#ifndef BHCL_KDTREE_COMMON_H
#define BHCL_KDTREE_COMMON_H

#include "knn_common.h"
#include "kdtree_layout.h"

#ifndef BHCL_KD_STACK
#define BHCL_KD_STACK 32
#endif

/* One step down the inner node `nd` (index `node`) for query q whose current cell lies at offsets
 * `off` (xyz) from it: returns the child on the query's side; sets the far child and the offsets
 * to its cell, with w their squared length summed as bhcl_dist2 sums (the far cell's lower bound:
 * every point in it has a float distance >= w, see kdtree_knn.cl). */
inline uint bhcl_kd_descend(bhcl_kd_node nd, uint node, float3 q, float4 off, uint* far_child,
                            float4* far_off) {
  float qd = nd.dim == 0u ? q.x : (nd.dim == 1u ? q.y : q.z);
  float diff = qd - nd.split;
  int go_left = diff < 0.0f;
  *far_child = go_left ? nd.a : node + 1u;
  float4 fo = off;
  if (nd.dim == 0u) fo.x = diff;
  else if (nd.dim == 1u) fo.y = diff;
  else fo.z = diff;
  fo.w = bhcl_dist2((float3)(0.0f), fo);
  *far_off = fo;
  return go_left ? node + 1u : nd.a;
}

/* The traversal: depth first from the root with a fixed-size private stack (no recursion), near
 * child first. A far child is deferred when its cell's lower bound is within the bound, and
 * dropped when the bound has shrunk below it by the time it would be popped. */
inline __attribute__((always_inline)) void bhcl_kd_search(__global const bhcl_kd_node* nodes,
                                                          __global const float4* points, float3 q,
                                                          BHCL_KD_STATE* st) {
  /* Deferred far children: xyz = offsets to the cell, w = its lower bound. */
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
      if (far_off.w <= BHCL_KD_BOUND(st)) {
        st_off[sp] = far_off;
        st_node[sp] = far_child;
        ++sp;
      }
      node = near_child;
      continue;
    }
    BHCL_KD_SCAN(st, nd.a, nd.a + nd.b);
    /* Next deferred cell that can still hold a candidate. */
    const float bound = BHCL_KD_BOUND(st);
    while (sp > 0 && st_off[sp - 1].w > bound) --sp;
    if (sp == 0) break;
    --sp;
    node = st_node[sp];
    off = st_off[sp];
  }
}

#endif /* BHCL_KDTREE_COMMON_H */
