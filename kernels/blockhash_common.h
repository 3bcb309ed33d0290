/* Block hashing: the arithmetic both block-hash kernels share (blockhash_knn.cl,
 * blockhash_cells_knn.cl). OpenCL C; the host reference (lib/src/blockhash/query_ref.cpp) repeats
 * each step in the same order so that results agree bit for bit. */
#ifndef BHCL_BLOCKHASH_COMMON_H
#define BHCL_BLOCKHASH_COMMON_H

#include "knn_common.h"
#include "blockhash_layout.h"

/* h_T(t) = #{i : t_i <= t}; thresholds ascending, +inf padded. */
inline uint bh_hash(__global const float* thr, uint P, float t) {
  uint lo = 0, hi = P;
  while (lo < hi) {
    uint mid = (lo + hi) >> 1;
    if (thr[mid] <= t) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

/* The adjacent cell on the side of the nearer face, or -1 when that side is unbounded. */
inline int bh_near_side(__global const float* thr, uint P, uint h, float t) {
  float lo = h > 0 ? thr[h - 1] : -INFINITY;
  float hi = h < P ? thr[h] : INFINITY;
  float dlo = t - lo, dhi = hi - t;
  if (dlo < dhi) return (int)h - 1;
  if (isfinite(dhi)) return (int)h + 1;
  return -1;
}

/* Squared distance from q to a block's box, in the order of bhcl_dist2: a lower bound of the
 * distance of every point in the box, rounding included (every step is monotone). */
inline float bh_box_dist2(float3 q, __global const bhcl_bh_box* b) {
  float ex = fmax(fmax(b->lo_x - q.x, 0.0f), q.x - b->hi_x);
  float ey = fmax(fmax(b->lo_y - q.y, 0.0f), q.y - b->hi_y);
  float ez = fmax(fmax(b->lo_z - q.z, 0.0f), q.z - b->hi_z);
  return ex * ex + ey * ey + ez * ez;
}

/* 3D Hilbert index of grid cell (x, y, z) < 2^bits (Skilling), as lib/src/sfc/hilbert.cpp. */
inline ulong bh_hilbert_encode(uint x0, uint x1, uint x2, uint bits) {
  uint X[3] = {x0, x1, x2};
  uint M = 1u << (bits - 1);
  for (uint Q = M; Q > 1; Q >>= 1) {
    uint P = Q - 1;
    for (int i = 0; i < 3; ++i) {
      if (X[i] & Q) {
        X[0] ^= P;
      } else {
        uint t = (X[0] ^ X[i]) & P;
        X[0] ^= t;
        X[i] ^= t;
      }
    }
  }
  X[1] ^= X[0];
  X[2] ^= X[1];
  uint t = 0;
  for (uint Q = M; Q > 1; Q >>= 1)
    if (X[2] & Q) t ^= Q - 1;
  X[0] ^= t;
  X[1] ^= t;
  X[2] ^= t;
  ulong key = 0;
  for (int b = (int)bits - 1; b >= 0; --b)
    for (int i = 0; i < 3; ++i) key = (key << 1) | (ulong)((X[i] >> b) & 1u);
  return key;
}

#endif /* BHCL_BLOCKHASH_COMMON_H */
