/* Block hashing: the device layouts shared by the host build and both block-hash kernels.
 * Valid OpenCL C and C++ (the host checks sizes and offsets with static_assert in
 * lib/src/blockhash/index.cpp).
 *
 * Memory of a built index (all arrays are flat buffers):
 *  - blocks:  one bhcl_bh_block (256 bytes) per block of X <= 16 points, in Hilbert order.
 *             Structure of arrays: x[16], y[16], z[16] hold the caller's exact float coordinates
 *             and id[16] the caller's original indices, so that one block is one 256-byte burst
 *             and a block scan reads 4 contiguous 64-byte lines (x, y, z, id) with unit stride.
 *             X = 16 fills the block (auto); the talk's X = 10 (paper) leaves slots 10..15 unused,
 *             as the talk's 10 x 24-byte photons leave 16 of 256 bytes unused.
 *  - boxes:   one bhcl_bh_box (32 bytes) per block: the block's bounding box and its point count.
 *             Kept apart from the blocks so that the box test of a block that is then skipped
 *             touches 32 bytes, not the block.
 *  - thresholds: L x 3 x P floats, (table, dimension, i); per (table, dimension) ascending and
 *             padded with +inf where guarding removed duplicates: h_T(t) = #{i : t_i <= t}.
 *  - directory (auto only): per table, the sorted uint32 keys of the occupied cells; the bucket
 *             of key j is bucket j of that table. Paper addresses all (P+1)^3 cells directly.
 *  - buckets: bhcl_bh_bucket (16 bytes) per cell (paper: every cell; auto: occupied cells).
 *  - refs:    int32 block references; bucket b owns refs[first_ref, first_ref + n_refs).
 *             Paper: fixed B slots per bucket (-1 padded), as the talk's memory formula assumes;
 *             auto: variable-length buckets, no padding.
 * A cell key is (hx * (P + 1) + hy) * (P + 1) + hz with P <= 1024, so it fits 32 bits. */
#ifndef BHCL_BLOCKHASH_LAYOUT_H
#define BHCL_BLOCKHASH_LAYOUT_H

#include "bhcl_shared.h"

/* Point slots of a block: 16 x (3 floats + 1 int32) = 256 bytes. */
#define BHCL_BH_BLOCK_SLOTS 16

/* The largest P (thresholds per dimension) so that cell keys fit 32 bits. */
#define BHCL_BH_MAX_P 1024

/* Bucket flags. */
#define BHCL_BH_FLAG_OVERFLOWED 1u /* more distinct blocks touched the cell than B */

typedef struct bhcl_bh_block {
  bhcl_f32 x[BHCL_BH_BLOCK_SLOTS];
  bhcl_f32 y[BHCL_BH_BLOCK_SLOTS];
  bhcl_f32 z[BHCL_BH_BLOCK_SLOTS];
  bhcl_i32 id[BHCL_BH_BLOCK_SLOTS];
} bhcl_bh_block;

typedef struct bhcl_bh_box {
  bhcl_f32 lo_x, lo_y, lo_z;
  bhcl_i32 count; /* points in the block, 1..X */
  bhcl_f32 hi_x, hi_y, hi_z;
  bhcl_i32 first; /* position of the block's first point in Hilbert order */
} bhcl_bh_box;

typedef struct bhcl_bh_bucket {
  bhcl_u32 first_ref; /* into refs */
  bhcl_u32 n_refs;    /* block references held, <= B */
  bhcl_i32 q;         /* Q = B - #blocks_inserted - #overflows; the priority is |Q|, smaller first */
  bhcl_u32 flags;     /* BHCL_BH_FLAG_* */
} bhcl_bh_bucket;

#endif /* BHCL_BLOCKHASH_LAYOUT_H */
