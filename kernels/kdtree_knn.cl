/* Exact kNN on a kd-tree built on the host: one work-item per query, depth-first traversal with a
 * fixed-size private stack (no recursion), near child first.
 *
 * Exactness (bit-equal to the brute-force kernel, ties to the lower original index):
 *  - A cell's lower bound is the squared length of the per-dimension offsets from the query to the
 *    split planes that separate it, summed in the order bhcl_dist2 uses. Float subtraction,
 *    squaring and addition are monotone, so every point in the cell has a float distance >= that
 *    bound: pruning a cell whose bound exceeds the k-th distance can never drop a candidate.
 *  - Cells are pruned only when bound > k-th distance (`<=` visits), so a point that ties the k-th
 *    distance with a lower index is still found.
 *  - Candidates are ranked by (distance, caller's index) with the shared top-k list.
 *
 * BHCL_KMAX: top-k capacity. BHCL_KD_STACK: stack entries, at least the tree's inner depth. */
#include "kdtree_common.h"

#ifndef BHCL_KD_STACK
#define BHCL_KD_STACK 32
#endif

__kernel void kdtree_knn(__global const bhcl_kd_node* nodes, __global const float4* points,
                         BHCL_KNN_QUERY_PARAMS, BHCL_KNN_RESULT_PARAMS) {
  BHCL_KNN_BEGIN;

  if (bhcl_query_is_finite(q)) {
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
        float bound = min(max_r2, bhcl_topk_bound(best_d, k));
        if (far_off.w <= bound) {
          st_off[sp] = far_off;
          st_node[sp] = far_child;
          ++sp;
        }
        node = near_child;
        continue;
      }
      /* An accepted point has d <= max_r2 and d <= the k-th distance: `bound` (kept in a
       * register) rejects most points before the list is read. */
      float bound = min(max_r2, bhcl_topk_bound(best_d, k));
      uint end = nd.a + nd.b;
      for (uint i = nd.a; i < end; ++i) {
        float4 p = points[i];
        float d = bhcl_dist2(q, p);
        if (d <= bound) {
          int idx = as_int(p.w);
          if (bhcl_topk_accepts(best_d, best_i, k, d, idx)) {
            nfound = bhcl_topk_push(best_d, best_i, k, nfound, d, idx);
            bound = min(max_r2, bhcl_topk_bound(best_d, k));
          }
        }
      }
      /* Next deferred cell that can still hold a candidate. */
      while (sp > 0 && st_off[sp - 1].w > bound) --sp;
      if (sp == 0) break;
      --sp;
      node = st_node[sp];
      off = st_off[sp];
    }
  }
  bhcl_write_row(out_ids, out_d2, out_counts, row, k, best_d, best_i);
}
