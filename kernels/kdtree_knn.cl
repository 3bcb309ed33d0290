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
#include "knn_common.h"

/* The top-k list as the traversal's state. */
typedef struct kd_topk {
  float* d;
  int* id;
  uint k, nfound;
  float max_r2;
} kd_topk;

/* An accepted point has d <= max_r2 and d <= the k-th distance: `bound` (kept in a register)
 * rejects most points before the list is read. */
inline __attribute__((always_inline)) void kd_topk_scan(kd_topk* t, __global const float4* points,
                                                        float3 q, uint a, uint e) {
  float bound = min(t->max_r2, bhcl_topk_bound(t->d, t->k));
  for (uint i = a; i < e; ++i) {
    float4 p = points[i];
    float d = bhcl_dist2(q, p);
    if (d <= bound) {
      int idx = as_int(p.w);
      if (bhcl_topk_accepts(t->d, t->id, t->k, d, idx)) {
        t->nfound = bhcl_topk_push(t->d, t->id, t->k, t->nfound, d, idx);
        bound = min(t->max_r2, bhcl_topk_bound(t->d, t->k));
      }
    }
  }
}

#define BHCL_KD_STATE kd_topk
#define BHCL_KD_BOUND(st) min((st)->max_r2, bhcl_topk_bound((st)->d, (st)->k))
#define BHCL_KD_SCAN(st, a, e) kd_topk_scan(st, points, q, a, e)
#include "kdtree_common.h"

__kernel void kdtree_knn(__global const bhcl_kd_node* nodes, __global const float4* points,
                         BHCL_KNN_QUERY_PARAMS, BHCL_KNN_RESULT_PARAMS) {
  BHCL_KNN_BEGIN;
  if (bhcl_query_is_finite(q)) {
    kd_topk t = {best_d, best_i, k, nfound, max_r2};
    bhcl_kd_search(nodes, points, q, &t);
  }
  bhcl_write_row(out_ids, out_d2, out_counts, bhcl_out_row(out_rows, remap, row), k, best_d, best_i);
}
