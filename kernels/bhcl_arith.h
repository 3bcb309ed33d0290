/* The arithmetic the kernels and their host references share: the squared distance, the top-k
 * ranking and insertion, block hashing's hash, near side and box distance, and the 3D Hilbert key.
 * Valid OpenCL C and valid C++ (the host references include it), so there is one definition of
 * each step instead of twins kept in step by hand; only the control flow of a query is written
 * twice (kernel and reference), and the bit-exact tests compare those.
 *
 * Bit-exact agreement needs unfused multiply-adds on both sides: the kernels say
 * FP_CONTRACT OFF below, the host library is compiled with -ffp-contract=off. */
#ifndef BHCL_ARITH_H
#define BHCL_ARITH_H

#include "bhcl_shared.h"
#include "blockhash_layout.h"

#ifdef __OPENCL_C_VERSION__
#pragma OPENCL FP_CONTRACT OFF
#define BHCL_GLOBAL __global
#define BHCL_FMAX fmax
#define BHCL_ISFINITE isfinite
typedef ulong bhcl_u64;
#else
#include <cmath>
#include <cstdint>
#define BHCL_GLOBAL
#define BHCL_FMAX std::fmax
#define BHCL_ISFINITE std::isfinite
typedef std::uint64_t bhcl_u64;
#endif

/* sum((q-p)^2), evaluated left to right: the contract's distance. */
inline float bhcl_dist2_xyz(float qx, float qy, float qz, float px, float py, float pz) {
  float dx = qx - px;
  float dy = qy - py;
  float dz = qz - pz;
  return dx * dx + dy * dy + dz * dz;
}

/* The ranking of every method: (d, i) before (d2, i2) when nearer, ties to the lower index. */
inline int bhcl_ranks_before(float d, bhcl_i32 i, float d2, bhcl_i32 i2) {
  return d < d2 || (d == d2 && i < i2);
}

/* A top-k list: d[] ascending by bhcl_ranks_before; empty slots are (+inf, BHCL_EMPTY_SLOT_ID).
 * True when (dist, idx) ranks before the current k-th entry. */
inline int bhcl_topk_accepts(const float* d, const bhcl_i32* id, bhcl_u32 k, float dist,
                             bhcl_i32 idx) {
  return bhcl_ranks_before(dist, idx, d[k - 1], id[k - 1]);
}

/* Inserts (dist, idx), which must be accepted, into a list that holds n entries (n <= k),
 * dropping the k-th entry of a full list. It starts at the first free slot while the list fills,
 * so the +inf tail is never shifted (at k = 50 the shifts cost ~30 % of a kernel). Returns the new
 * count. */
inline bhcl_u32 bhcl_topk_push(float* d, bhcl_i32* id, bhcl_u32 k, bhcl_u32 n, float dist,
                               bhcl_i32 idx) {
  bhcl_u32 j = n < k ? n : k - 1;
  while (j > 0 && bhcl_ranks_before(dist, idx, d[j - 1], id[j - 1])) {
    d[j] = d[j - 1];
    id[j] = id[j - 1];
    --j;
  }
  d[j] = dist;
  id[j] = idx;
  return n < k ? n + 1 : n;
}

/* Block hashing's hash h_T(t) = #{i : t_i <= t}: thresholds ascending, +inf padded; 0 below t_0,
 * P at or above the last threshold (the clamp). */
inline bhcl_u32 bh_hash(BHCL_GLOBAL const float* thr, bhcl_u32 P, float t) {
  bhcl_u32 lo = 0, hi = P;
  while (lo < hi) {
    bhcl_u32 mid = (lo + hi) >> 1;
    if (thr[mid] <= t) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

/* The adjacent cell on the side of the nearer cell face, or -1 when that side is unbounded (the
 * clamp cells' outer side, or a dimension without thresholds). */
inline int bh_near_side(BHCL_GLOBAL const float* thr, bhcl_u32 P, bhcl_u32 h, float t) {
  float lo = h > 0 ? thr[h - 1] : -INFINITY;
  float hi = h < P ? thr[h] : INFINITY;
  float dlo = t - lo, dhi = hi - t;
  if (dlo < dhi) return (int)h - 1;
  if (BHCL_ISFINITE(dhi)) return (int)h + 1;
  return -1;
}

/* Squared distance from q to a block's box, in the order of bhcl_dist2_xyz: a lower bound of the
 * distance of every point in the box, rounding included (every step is monotone). */
inline float bh_box_dist2_xyz(float qx, float qy, float qz, BHCL_GLOBAL const bhcl_bh_box* b) {
  float ex = BHCL_FMAX(BHCL_FMAX(b->lo_x - qx, 0.0f), qx - b->hi_x);
  float ey = BHCL_FMAX(BHCL_FMAX(b->lo_y - qy, 0.0f), qy - b->hi_y);
  float ez = BHCL_FMAX(BHCL_FMAX(b->lo_z - qz, 0.0f), qz - b->hi_z);
  return ex * ex + ey * ey + ez * ez;
}

/* 3D Hilbert index of grid cell (x0, x1, x2), each < 2^bits, 1 <= bits <= 21 (Skilling,
 * "Programming the Hilbert curve", AIP Conf. Proc. 707, 2004: axes -> transposed index, then the
 * bits interleaved). The space-filling-curve module (lib/src/sfc) decodes it. */
inline bhcl_u64 bh_hilbert_encode(bhcl_u32 x0, bhcl_u32 x1, bhcl_u32 x2, bhcl_u32 bits) {
  bhcl_u32 X[3];
  X[0] = x0;
  X[1] = x1;
  X[2] = x2;
  bhcl_u32 M = 1u << (bits - 1);
  for (bhcl_u32 Q = M; Q > 1; Q >>= 1) {
    bhcl_u32 P = Q - 1;
    for (int i = 0; i < 3; ++i) {
      if (X[i] & Q) {
        X[0] ^= P;
      } else {
        bhcl_u32 t = (X[0] ^ X[i]) & P;
        X[0] ^= t;
        X[i] ^= t;
      }
    }
  }
  X[1] ^= X[0];
  X[2] ^= X[1];
  bhcl_u32 t = 0;
  for (bhcl_u32 Q = M; Q > 1; Q >>= 1)
    if (X[2] & Q) t ^= Q - 1;
  X[0] ^= t;
  X[1] ^= t;
  X[2] ^= t;
  bhcl_u64 key = 0;
  for (int b = (int)bits - 1; b >= 0; --b)
    for (int i = 0; i < 3; ++i) key = (key << 1) | (bhcl_u64)((X[i] >> b) & 1u);
  return key;
}

#endif /* BHCL_ARITH_H */
