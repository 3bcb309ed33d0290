/* What the kd-tree kernels share (kdtree_knn.cl, kdtree_radius.cl). OpenCL C. */
#ifndef BHCL_KDTREE_COMMON_H
#define BHCL_KDTREE_COMMON_H

#include "knn_common.h"
#include "kdtree_layout.h"

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

#endif /* BHCL_KDTREE_COMMON_H */
