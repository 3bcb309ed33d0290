/* Pieces every radius-search kernel shares (one work-item per query, two passes over the same
 * points: pass 0 counts the points within r, pass 1 writes them where the host's prefix sum of
 * the counts says). OpenCL C; the arithmetic is in bhcl_arith.h.
 *
 * Why count then fill: the sizes are not known in advance, and a second visit of the same blocks
 * or leaves costs less than a device-side allocator or a fixed worst-case slice per query. */
#ifndef BHCL_RADIUS_COMMON_H
#define BHCL_RADIUS_COMMON_H

#include "knn_common.h"

/* The parameters of every radius kernel, in the order the host's Index::radius_search sets them
 * (lib/src/core/radius.cpp): the query rows [first, first + count) of the query buffer, the
 * squared radius, the pass, per query the start of its slice in the fill buffers (indexed by
 * row - first; pass 1 only), per row the count (written by pass 0, read back as the fill limit by
 * pass 1), the fill buffers, and the examined counts (pass 0, when want_examined). */
#define BHCL_RADIUS_PARAMS                                                                   \
  __global const float *queries, ulong first, uint count, float r2, uint fill,               \
      __global const ulong *offsets, __global int *out_counts, __global int *out_ids,         \
      __global float *out_d2, __global int *out_examined, uint want_examined

/* The opening of a radius kernel: the work-item's row, query q, and its slice (base, limit). */
#define BHCL_RADIUS_BEGIN                                          \
  uint gid = get_global_id(0);                                     \
  if (gid >= count) return;                                        \
  ulong row = first + gid;                                         \
  float3 q = bhcl_load_query(queries, row);                        \
  ulong base = fill ? offsets[gid] : 0;                            \
  uint limit = fill ? (uint)out_counts[row] : 0u;                  \
  uint found = 0

/* One point within r: written in the fill pass (never past the count the first pass found: the
 * passes visit the same points, the limit guards the buffers if they did not), counted in both. */
inline void bhcl_radius_emit(uint fill, __global int* out_ids, __global float* out_d2, ulong base,
                             uint limit, uint* found, float d, int id) {
  if (fill && *found < limit) {
    out_ids[base + *found] = id;
    out_d2[base + *found] = d;
  }
  ++*found;
}

/* A query's slice as one value, for the traversals that take a state (grid_search.h,
 * kdtree_common.h): the squared radius, the pass, where the points within it go, and how many
 * were found. BHCL_RADIUS_SLICE initializes it from BHCL_RADIUS_PARAMS and BHCL_RADIUS_BEGIN. */
typedef struct bhcl_radius_slice {
  float r2;
  uint fill, limit, found;
  ulong base;
  __global int* out_ids;
  __global float* out_d2;
} bhcl_radius_slice;

#define BHCL_RADIUS_SLICE {r2, fill, limit, 0u, base, out_ids, out_d2}

inline void bhcl_slice_emit(bhcl_radius_slice* s, float d, int id) {
  bhcl_radius_emit(s->fill, s->out_ids, s->out_d2, s->base, s->limit, &s->found, d, id);
}

/* The close of a radius kernel: the count (pass 0) and the examined points. */
#define BHCL_RADIUS_END(examined)                            \
  if (!fill) {                                               \
    out_counts[row] = (int)found;                            \
    if (want_examined) out_examined[row] = (int)(examined);  \
  }

#endif /* BHCL_RADIUS_COMMON_H */
