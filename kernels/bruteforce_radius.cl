/* Exact radius search by brute force: one work-item per query, every point tested. The points
 * are float4, w = the point's id (int bits), ascending, so a query's points come out in id order;
 * removed ones (updates) are skipped by their ids' marks in `removed`. */
#include "radius_common.h"

__kernel void bruteforce_radius(__global const float4* points, uint n_points, __global const uint* removed,
                                uint removed_words, BHCL_RADIUS_PARAMS) {
  BHCL_RADIUS_BEGIN;
  if (bhcl_query_is_finite(q)) {
    for (uint i = 0; i < n_points; ++i) {
      float d = bhcl_dist2(q, points[i]);
      if (d <= r2 && !bhcl_id_removed(removed, removed_words, as_uint(points[i].w)))  /* removed: marked */
        bhcl_radius_emit(fill, out_ids, out_d2, base, limit, &found, d, as_int(points[i].w));
    }
  }
  BHCL_RADIUS_END(found);
}
