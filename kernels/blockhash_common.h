/* Block hashing: what both block-hash kernels share (blockhash_knn.cl, blockhash_cells_knn.cl)
 * beyond the arithmetic of bhcl_arith.h, which the host reference (lib/src/blockhash/query_ref.cpp)
 * includes too. OpenCL C. */
#ifndef BHCL_BLOCKHASH_COMMON_H
#define BHCL_BLOCKHASH_COMMON_H

#include "knn_common.h"
#include "blockhash_layout.h"

/* The box distance on vector types (bhcl_arith.h holds the arithmetic). */
inline float bh_box_dist2(float3 q, __global const bhcl_bh_box* b) {
  return bh_box_dist2_xyz(q.x, q.y, q.z, b);
}

#endif /* BHCL_BLOCKHASH_COMMON_H */
