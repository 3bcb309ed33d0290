/* Block hashing, grid layout (the auto preset): the geometry and the search loop that the kernels
 * (blockhash_grid_knn.cl, blockhash_grid_radius.cl) and their host reference
 * (lib/src/blockhash/grid_query_ref.cpp) share. Valid OpenCL C and valid C++: one definition of
 * the traversal for both sides, so that the reference equals the kernel bit for bit.
 *
 * The layout. Cubic cells of side h over the points' box, nx x ny x nz of them, numbered
 * c = (z ny + y) nx + x (x fastest). The points are sorted by cell (stable: ties by the caller's
 * index) into structure-of-arrays x[], y[], z[], id[]; start(c) is the first point of cell c and
 * start(c + 1) its end (the directory of the cells: below). So the cells of a row (fixed y, z) are adjacent in
 * memory and a run of cells x0..x1 of a row is the one contiguous range
 * [start(c(x0)), start(c(x1) + 1)): the talk's blocks are the cells (its "alternative
 * clustering" future work), the bucket of a cell is its run.
 *
 * The search. Ring r around the query's home cell is the cells at Chebyshev distance r; its rows
 * (offsets 0, -1, +1, -2, ...) are each clipped at both ends to the cells whose slab distance is
 * within the current bound (the k-th distance, or the radius) and gathered as one run, then the
 * runs are scanned nearest first (by the row's slab distance) while within the bound. After ring r the search stops when the bound lies inside the box of the rings
 * visited (exact), when the rings cover the grid, or (budget) when `budget` points are examined:
 * a run is scanned when fewer than `budget` points were examined before it.
 *
 * Before including this header the includer defines the search state:
 *   BHCL_GRID_STATE           the state's type (a top-k list, or a radius emitter)
 *   BHCL_GRID_BOUND(st)       float: the squared distance a point must be within to matter
 *   BHCL_GRID_SCAN(st, a, b)  scans sorted points [a, b) (px, py, pz, pid and q in scope)
 * and may define BHCL_GRID_SCAN_WALK(st, a, b), the same for the far walk's runs (default
 * BHCL_GRID_SCAN; the kNN kernel's scans few points one at a time there).
 */
#ifndef BHCL_GRID_SEARCH_H
#define BHCL_GRID_SEARCH_H

#include "bhcl_arith.h"

#ifdef __OPENCL_C_VERSION__
#define BHCL_GRID_INLINE inline __attribute__((always_inline))
#define BHCL_FMIN fmin
#else
#include <algorithm>
#define BHCL_GRID_INLINE inline
#define BHCL_FMIN std::fmin
#endif

/* The grid's geometry, as the host builds it and the kernels receive it (three vector arguments:
 * (ox, oy, oz, h), (inv_h, margin, 0, 0), (nx, ny, nz, 0)). margin: every slab distance is
 * lowered by it, so that a point whose cell the float division rounded into a neighbour is still
 * inside its cell's slabs: the slab distances stay lower bounds and the exact mode exact. */
typedef struct bhcl_grid_geom {
  float ox, oy, oz, h;
  float inv_h, margin;
  bhcl_u32 nx, ny, nz;
  bhcl_u32 sparse; /* 0: starts is the direct table; BHCL_GRID_SEG_BITS: the two-level directory */
} bhcl_grid_geom;

/* The box of the stored points (each side exactly a point's coordinate; loose after removes).
 * The walk's slab distances are taken to the part of a slab inside it: a cell is a whole side h
 * thick even where every point lies on one plane, and a query far above that plane would
 * otherwise see every cell within sqrt(2 D h) of its foot as within reach. */
typedef struct bhcl_grid_dbox {
  float lx, ly, lz, hx, hy, hz;
} bhcl_grid_dbox;

/* The directory of the cells. Direct: starts[c] for every cell c (ncells + 1 entries). Where that
 * table would be too large (points on surfaces in a large box: 10M points of the Cornell box make
 * 72M cells, 4 % of them occupied) it is two-level over segments of 2^BHCL_GRID_SEG_BITS cells of
 * a row: starts[s] for segment s (ncells / 16 + 1 entries) is, for a segment holding no point,
 * BHCL_GRID_EMPTY_SEG | (the start of its cells: all equal), else the index in starts itself of
 * the segment's 16 starts. A run's two ends cost two dependent loads each instead of one, and
 * the table shrinks to about 4 bytes per 16 cells plus 64 bytes per occupied segment. */
#define BHCL_GRID_SEG_BITS 4u
#define BHCL_GRID_EMPTY_SEG 0x80000000u

#ifdef __OPENCL_C_VERSION__
/* The geometry from the kernels' three arguments (the host's order: see bhcl_grid_geom). */
inline bhcl_grid_geom bhcl_grid_geom_from(float4 geo0, float4 geo1, uint4 dims) {
  /* In bhcl_grid_geom's field order: origin and side, 1/side and margin, the dimensions. */
  const bhcl_grid_geom g = {geo0.x, geo0.y, geo0.z, geo0.w, geo1.x, geo1.y, dims.x, dims.y, dims.z, dims.w};
  return g;
}
inline bhcl_grid_dbox bhcl_grid_dbox_from(float4 lo, float4 hi) {
  const bhcl_grid_dbox b = {lo.x, lo.y, lo.z, hi.x, hi.y, hi.z};  /* the field order of bhcl_grid_dbox */
  return b;
}
#endif

/* max(a, b) as a select: the walk's slab and box distances (bhcl_grid_slabs_in, bhcl_grid_box_dist)
 * never see a NaN (the query is finite, a side is a finite coordinate or an empty box's +-inf, so
 * no inf - inf), where fmax's NaN rule cost two more instructions each on x86 (AVX-512: vmaxss,
 * not vmaxss + vcmpunordss + vblendvps); the same values. Host reference, two clusters: -0.9 % of
 * the instructions at k = 10. */
BHCL_GRID_INLINE float bhcl_grid_maxf(float a, float b) { return a > b ? a : b; }

/* The cell of coordinate t along an axis of n cells from origin o: floor((t - o) / h), clamped. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_cell(float t, float o, float inv_h, bhcl_u32 n) {
  float f = (t - o) * inv_h;
  if (!(f > 0.0f)) return 0u;
  if (f >= (float)(n - 1u)) return n - 1u;
  return (bhcl_u32)f;
}

/* Distance from t to the slab of cells i0..i1 (lowered by the margin, never negative). The ends
 * are cell i0's low side and cell i1's high side computed as for those cells alone, so the range's
 * distance never exceeds any of its cells' (o + i h is monotone in i in floats too). */
BHCL_GRID_INLINE float bhcl_grid_slabs(float t, float o, float h, float margin, bhcl_u32 i0, bhcl_u32 i1) {
  float lo = o + (float)i0 * h;
  float hi = o + (float)(i1 + 1u) * h;
  float e = BHCL_FMAX(BHCL_FMAX(lo - t, t - hi), 0.0f) - margin;
  return BHCL_FMAX(e, 0.0f);
}

/* As bhcl_grid_slabs, the slab clipped to [dl, dh] (the points' box along the axis). A side
 * that is the box's needs no margin: every point p has p >= dl, so fl(p - t) >= fl(dl - t)
 * (rounding is monotone), and the distance stays a lower bound of every point's to the bit. */
BHCL_GRID_INLINE float bhcl_grid_slabs_in(float t, float o, float h, float margin, bhcl_u32 i0, bhcl_u32 i1,
                                          float dl, float dh) {
  float lo = o + (float)i0 * h, hi = o + (float)(i1 + 1u) * h;
  float mlo = margin, mhi = margin;
  if (dl >= lo) lo = dl, mlo = 0.0f;
  if (dh <= hi) hi = dh, mhi = 0.0f;
  return bhcl_grid_maxf(bhcl_grid_maxf((lo - t) - mlo, (t - hi) - mhi), 0.0f);
}

/* x squared, as its own rounding (FP_CONTRACT OFF): a sum of squares made from it is the same. */
BHCL_GRID_INLINE float bhcl_grid_sq(float x) { return x * x; }

/* Distance from t to the slab of cell i (lowered by the margin, never negative). */
BHCL_GRID_INLINE float bhcl_grid_slab(float t, float o, float h, float margin, bhcl_u32 i) {
  return bhcl_grid_slabs(t, o, h, margin, i, i);
}

/* The distance from t to the outside of cells [c - r, c + r] of an axis of n cells (lowered by
 * the margin); +inf on a side where the range reaches the grid's end (nothing lies beyond). */
BHCL_GRID_INLINE float bhcl_grid_reach(float t, float o, float h, float margin, bhcl_u32 c,
                                       bhcl_u32 r, bhcl_u32 n) {
  float w = INFINITY;
  if (c > r) w = t - (o + (float)(c - r) * h);
  if (c + r + 1u < n) w = BHCL_FMIN(w, (o + (float)(c + r + 1u) * h) - t);
  return w - margin;
}

/* The first sorted point of cell c (c = ncells: the point count), through either directory. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_start(BHCL_GLOBAL const bhcl_u32* starts, bhcl_u32 sparse, bhcl_u32 c) {
  if (!sparse) return starts[c];
  const bhcl_u32 e = starts[c >> BHCL_GRID_SEG_BITS];
  return (e & BHCL_GRID_EMPTY_SEG) ? (e & ~BHCL_GRID_EMPTY_SEG)
                                   : starts[e + (c & ((1u << BHCL_GRID_SEG_BITS) - 1u))];
}

/* Row offset j of a ring (0, -1, +1, -2, +2, ...). */
BHCL_GRID_INLINE int bhcl_grid_offset(int j) { return (j & 1) ? -((j + 1) >> 1) : (j >> 1); }

/* The rings' squared slab distances of the cells within BHCL_GRID_NEAR of the query's cell, per
 * axis, each made once (at the ring of its offset) and kept in a private array; the rows of those
 * rings read them. Without it every row made its own: a slab is about 15 instructions (two
 * conversions, the ends, the margin), and ring 1's nine rows asked for 30 of them where 6 are
 * distinct. The same values (each the square of bhcl_grid_slab, summed as before). 0: none (the
 * forms without private arrays). */
#ifndef BHCL_GRID_NEAR
#define BHCL_GRID_NEAR 0
#endif

/* The occupancy pyramid: the empty space a far query skips. Level l >= 1 has
 * ((n - 1) >> l) + 1 nodes along an axis of n cells; node (X, Y, Z) of level l covers the fine
 * cells [X << l, (X + 1) << l) of each axis (clipped to the grid), and its byte has bit
 * bx | by << 1 | bz << 2 set when its child (2X + bx, 2Y + by, 2Z + bz) of level l - 1 (level 0:
 * the fine cells) holds a stored point (a cell whose run is not empty). The levels are stored one
 * after the other from level 1, each x fastest; the top is the first level with a single node.
 * About ncells / 7 bytes in all. Built on the host (lib/src/blockhash/grid_occupancy.cpp). */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_dim(bhcl_u32 n, bhcl_u32 l) { return ((n - 1u) >> l) + 1u; }

/* The bytes of level l. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_size(const bhcl_grid_geom g, bhcl_u32 l) {
  return bhcl_grid_occ_dim(g.nx, l) * bhcl_grid_occ_dim(g.ny, l) * bhcl_grid_occ_dim(g.nz, l);
}

/* The top level; *top_off: its node's byte, *total: the pyramid's bytes. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_top(const bhcl_grid_geom g, bhcl_u32* top_off, bhcl_u32* total) {
  bhcl_u32 l = 1u, off = 0u;
  while (bhcl_grid_occ_size(g, l) > 1u) off += bhcl_grid_occ_size(g, l++);
  *top_off = off;
  *total = off + 1u;
  return l;
}

/* The byte of node (X, Y, Z) of level l, whose level starts at byte off. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_index(const bhcl_grid_geom g, bhcl_u32 off, bhcl_u32 l, bhcl_u32 X,
                                              bhcl_u32 Y, bhcl_u32 Z) {
  return off + (Z * bhcl_grid_occ_dim(g.ny, l) + Y) * bhcl_grid_occ_dim(g.nx, l) + X;
}

/* The points' box of every pyramid node of level 2 or above (4^3 fine cells and up), after the
 * pyramid's bytes (from the first multiple of 4): six floats (lx, ly, lz, hx, hy, hz: each side a
 * stored point's coordinate, holes left out; an empty node's is inverted) for the node whose byte
 * is b at index b - (level 1's bytes), so level 2's come first. Why: over a surface the points lie
 * on a thin slab of a cell, and a node's slabs, a whole cell or node thick, let a query above it
 * see every cell within sqrt(2 D h) of its foot as within reach (k = 1 over Autzen's box examined
 * 90 points, 4 cells); the walk clips a node's slabs to its own box and its children's (down to
 * the fine cells) to their level-2 ancestor's. Present when level 2 exists (about ncells / 150
 * bytes); BHCL_GRID_TBOX 0 ignores them (an experiment: the host reference follows 1). */
#ifndef BHCL_GRID_TBOX
#define BHCL_GRID_TBOX 1
#endif
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_tbox_off(bhcl_u32 pyramid_bytes) { return (pyramid_bytes + 3u) & ~3u; }

/* The occupancy buffer's bytes: the pyramid and, when level 2 exists, the boxes. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_bytes(const bhcl_grid_geom g) {
  bhcl_u32 top_off, total;
  const bhcl_u32 top = bhcl_grid_occ_top(g, &top_off, &total);
  if (top < 2u) return total;
  return bhcl_grid_tbox_off(total) + 24u * (total - bhcl_grid_occ_size(g, 1u));
}

/* Box i of the occupancy buffer whose boxes start at byte off. */
#ifdef __OPENCL_C_VERSION__
inline bhcl_grid_dbox bhcl_grid_tbox_load(BHCL_GLOBAL const bhcl_u8* occ, bhcl_u32 off, bhcl_u32 i) {
  BHCL_GLOBAL const float* f = (BHCL_GLOBAL const float*)(occ + off) + 6u * i;
  const bhcl_grid_dbox b = {f[0], f[1], f[2], f[3], f[4], f[5]}; /* bhcl_grid_dbox's field order */
  return b;
}
#else
inline bhcl_grid_dbox bhcl_grid_tbox_load(const bhcl_u8* occ, bhcl_u32 off, bhcl_u32 i) {
  bhcl_grid_dbox b;
  std::memcpy(&b, occ + off + 24u * i, sizeof b); /* bytes, not a float array: no aliasing */
  return b;
}
#endif

/* The child (bx | by << 1 | bz << 2) of node (X, Y, Z) of level m + 1 on the side of the query's
 * (clamped) cell (cx, cy, cz) along each axis: the near child of BHCL_GRID_OCC_ORDER. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_near(bhcl_u32 cx, bhcl_u32 cy, bhcl_u32 cz, bhcl_u32 X, bhcl_u32 Y,
                                             bhcl_u32 Z, bhcl_u32 m) {
  return (cx >= ((2u * X + 1u) << m) ? 1u : 0u) | (cy >= ((2u * Y + 1u) << m) ? 2u : 0u) |
         (cz >= ((2u * Z + 1u) << m) ? 4u : 0u);
}

/* The rings around the home cell searched before the walk down the pyramid takes over (the
 * kernels' define; the host reference is passed the same value; 0xffffffff: the rings alone). */
#ifndef BHCL_GRID_FINE_RINGS
#define BHCL_GRID_FINE_RINGS 2u
#endif
/* Past them, the rings continue while the bound is within this many more rings of the stop, */
#ifndef BHCL_GRID_RING_SLACK
#define BHCL_GRID_RING_SLACK 2u
#endif
/* for at most this many more rings. */
#ifndef BHCL_GRID_RING_CAP
#define BHCL_GRID_RING_CAP 6u
#endif

/* Where the walk takes over at once for a query whose home cell's 4^3 block (a level-2 node of
 * the pyramid) holds no point: 2, after ring 0 found the home cell empty (one cell looked up
 * first); 1, before the rings; 0, never (the first rings run). Same rows either way. Tested
 * before the rings (1), the test cost the kernel on queries among the points 10-16 % (k = 10,
 * Cornell, sorted: bench/results/harness/home_skip_perf.txt): not the test's own instructions
 * (under 1 % of the samples) but the code the compiler made of the search around a way into the
 * walk ahead of the rings; after ring 0 the rings compile as without it. */
#ifndef BHCL_GRID_HOME_SKIP
#define BHCL_GRID_HOME_SKIP 2
#endif

/* The order in which the walk visits a node's 8 children: child BHCL_GRID_OCC_ORDER(p) ^ near
 * (near: the child on the query's side along each axis) at position p, i.e. the near child, the
 * three across one face, across an edge, the far one. The order is its own inverse (it swaps 3
 * and 4 only), so the position of child o is BHCL_GRID_OCC_ORDER(o ^ near). */
#define BHCL_GRID_OCC_ORDER(p) ((0x76534210u >> (4u * (p))) & 15u)

/* The lowest set bit's position of a nonzero x (OpenCL 1.2 has clz, not ctz). */
#ifdef __OPENCL_C_VERSION__
#define BHCL_GRID_CTZ(x) (31u - clz((x) & (0u - (x))))
#define BHCL_GRID_CLZ(x) ((bhcl_u32)clz(x))
#else
#define BHCL_GRID_CTZ(x) ((bhcl_u32)__builtin_ctz(x))
#define BHCL_GRID_CLZ(x) ((bhcl_u32)__builtin_clz(x))
#endif

/* A node's children that hold points (its occupancy byte), as bits by visiting position: bit p
 * set when child BHCL_GRID_OCC_ORDER(p) ^ near is, so that the walk steps from set bit to set
 * bit instead of testing all eight. The byte's bits j ^ near brought to j (three conditional
 * swaps: of bits, pairs, nibbles), then positions 3 and 4 swapped (the order's one exchange). */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_occ_pending(bhcl_u32 mask, bhcl_u32 near) {
  bhcl_u32 m = mask;
  m = (near & 1u) ? (((m & 0x55u) << 1) | ((m >> 1) & 0x55u)) : m;
  m = (near & 2u) ? (((m & 0x33u) << 2) | ((m >> 2) & 0x33u)) : m;
  m = (near & 4u) ? (((m & 0x0fu) << 4) | ((m >> 4) & 0x0fu)) : m;
  return (m & 0xe7u) | ((m & 0x08u) << 1) | ((m & 0x10u) >> 1);
}

#endif /* BHCL_GRID_SEARCH_H */

/* The search itself, once per translation unit that defines a state (the geometry above may have
 * been included before without one). */
#if defined(BHCL_GRID_STATE) && !defined(BHCL_GRID_SEARCH_FN)
#define BHCL_GRID_SEARCH_FN
#ifndef BHCL_GRID_SCAN_WALK
#define BHCL_GRID_SCAN_WALK(st, a, b) BHCL_GRID_SCAN(st, a, b)
#endif
#ifndef BHCL_GRID_ROWBUF
#define BHCL_GRID_ROWBUF 32
#endif
/* The depth-first walk keeps the level-2 box its children clip to across them (one load per
 * level-2 node), except in the kNN kernel's GPU form (BHCL_GRID_WALKCAP 0: no private arrays,
 * registers scarce), which reads it per child: 5 registers fewer on sm_90. Same distances. An
 * includer may set it (the radius kernel: 0). */
#ifndef BHCL_GRID_KEEP_BOX2
#if defined(BHCL_GRID_WALKCAP) && BHCL_GRID_WALKCAP == 0
#define BHCL_GRID_KEEP_BOX2 0
#else
#define BHCL_GRID_KEEP_BOX2 1
#endif
#endif

/* Runs [a, b) of a ring gathered for a nearest-first scan (row distance d), at most `cap`. */
typedef struct bhcl_grid_rows {
  float d[BHCL_GRID_ROWBUF];
  bhcl_u32 a[BHCL_GRID_ROWBUF], b[BHCL_GRID_ROWBUF];
} bhcl_grid_rows;

/* One run of the ring: into the sorted buffer (stable: equal distances keep their visit order),
 * or, with the buffer full (or cap 0), scanned at once. Returns 0 when the budget stops the search. */
#define BHCL_GRID_RUN(d_, a_, b_)                                                   \
  if ((a_) < (b_)) {                                                                \
    if (nr < cap) {                                                                 \
      bhcl_u32 j = nr++;                                                            \
      while (j > 0 && rows.d[j - 1] > (d_)) {                                       \
        rows.d[j] = rows.d[j - 1];                                                  \
        rows.a[j] = rows.a[j - 1];                                                  \
        rows.b[j] = rows.b[j - 1];                                                  \
        --j;                                                                        \
      }                                                                             \
      rows.d[j] = (d_);                                                             \
      rows.a[j] = (a_);                                                             \
      rows.b[j] = (b_);                                                             \
    } else {                                                                        \
      if (examined >= budget) return examined;                                      \
      BHCL_GRID_SCAN(st, (a_), (b_));                                               \
      examined += (b_) - (a_);                                                      \
    }                                                                               \
  }

/* The search of one query (finite q): returns the points examined. cap (<= BHCL_GRID_ROWBUF):
 * the runs of a ring gathered and scanned nearest first (0: each run scanned as it is met, the
 * GPU form, no private array); the kernel and the reference must use the same cap. */
/* The walk's geometry, fixed per query: the grid, the points' box, the query, its clamped cell
 * and the cube of cells [v0, v1] the rings have accounted for (empty: v0 > v1 along x). */
typedef struct bhcl_grid_walk_ctx {
  bhcl_grid_geom g;
  bhcl_grid_dbox db;
  float qx, qy, qz;
  bhcl_u32 cx, cy, cz;
  bhcl_u32 vx0, vy0, vz0, vx1, vy1, vz1;
  BHCL_GLOBAL const bhcl_u8* occ;
  bhcl_u32 size1, tboff; /* level 1's bytes; the boxes' first byte (0: no boxes, or not used) */
  bhcl_u32 rows;         /* 1: a level-2 node is scanned by its rows (bhcl_grid_walk_block) */
} bhcl_grid_walk_ctx;

/* The points' box of the level-2 node (X, Y, Z) (the walk's boxes are on: w->tboff != 0). */
BHCL_GRID_INLINE bhcl_grid_dbox bhcl_grid_walk_box2(const bhcl_grid_walk_ctx* w, bhcl_u32 X, bhcl_u32 Y, bhcl_u32 Z) {
  return bhcl_grid_tbox_load(w->occ, w->tboff, bhcl_grid_occ_index(w->g, w->size1, 2u, X, Y, Z) - w->size1);
}

/* The squared distance from the query to box b (0 inside): a lower bound of every point in b to
 * the bit, as each side is a stored point's coordinate (rounding is monotone). An inverted box
 * (a node whose points are all holes) is +inf away. */
BHCL_GRID_INLINE float bhcl_grid_box_dist(const bhcl_grid_walk_ctx* w, const bhcl_grid_dbox b) {
  const float ex = bhcl_grid_maxf(bhcl_grid_maxf(b.lx - w->qx, w->qx - b.hx), 0.0f);
  const float ey = bhcl_grid_maxf(bhcl_grid_maxf(b.ly - w->qy, w->qy - b.hy), 0.0f);
  const float ez = bhcl_grid_maxf(bhcl_grid_maxf(b.lz - w->qz, w->qz - b.hz), 0.0f);
  return ex * ex + ey * ey + ez * ez;
}

/* Child o of node (X, Y, Z) of level m + 1: its squared distance from the query (a lower bound of
 * its points'), or -1 when the rings have searched all of it. *u: the child's coordinates; moff:
 * the first byte of level m (read for m >= 2 only). With the boxes (w->tboff), a child of level
 * m >= 2 is as far as its own points' box (which holds every point of it, so no cell slab can
 * be tighter: one load and three clamps, no slab arithmetic); a lower child's slabs are clipped
 * to its level-2 ancestor's box, *b2 (the caller's copy, loaded once per level-2 node; null:
 * loaded here). Without them the slabs are clipped to the points' box. Either way the distance
 * stays a lower bound to the bit (bhcl_grid_slabs_in, bhcl_grid_box_dist). */
BHCL_GRID_INLINE float bhcl_grid_walk_child(const bhcl_grid_walk_ctx* w, bhcl_u32 m, bhcl_u32 moff, bhcl_u32 X,
                                            bhcl_u32 Y, bhcl_u32 Z, bhcl_u32 o, bhcl_u32* ux, bhcl_u32* uy,
                                            bhcl_u32* uz, const bhcl_grid_dbox* b2) {
  *ux = 2u * X + (o & 1u);
  *uy = 2u * Y + ((o >> 1) & 1u);
  *uz = 2u * Z + (o >> 2);
  const bhcl_u32 x0 = *ux << m, y0 = *uy << m, z0 = *uz << m;
  bhcl_u32 x1 = ((*ux + 1u) << m) - 1u, y1 = ((*uy + 1u) << m) - 1u, z1 = ((*uz + 1u) << m) - 1u;
  if (x1 >= w->g.nx) x1 = w->g.nx - 1u;
  if (y1 >= w->g.ny) y1 = w->g.ny - 1u;
  if (z1 >= w->g.nz) z1 = w->g.nz - 1u;
  if (x0 >= w->vx0 && x1 <= w->vx1 && y0 >= w->vy0 && y1 <= w->vy1 && z0 >= w->vz0 && z1 <= w->vz1) return -1.0f;
  bhcl_grid_dbox b = w->db;
  if (w->tboff) {
    if (m >= 2u)
      return bhcl_grid_box_dist(w, bhcl_grid_tbox_load(w->occ, w->tboff,
                                                       bhcl_grid_occ_index(w->g, moff, m, *ux, *uy, *uz) - w->size1));
    const bhcl_u32 s = 2u - m; /* up to the level-2 ancestor */
    b = b2 ? *b2 : bhcl_grid_walk_box2(w, *ux >> s, *uy >> s, *uz >> s);
  }
  const float ex = bhcl_grid_slabs_in(w->qx, w->g.ox, w->g.h, w->g.margin, x0, x1, b.lx, b.hx);
  const float ey = bhcl_grid_slabs_in(w->qy, w->g.oy, w->g.h, w->g.margin, y0, y1, b.ly, b.hy);
  const float ez = bhcl_grid_slabs_in(w->qz, w->g.oz, w->g.h, w->g.margin, z0, z1, b.lz, b.hz);
  return ex * ex + ey * ey + ez * ez;
}

/* Along one axis of n cells, the children 2U and 2U + 1 of level m whose cells
 * [u << m, min(((u + 1) << m) - 1, n - 1)] lie inside [v0, v1], as bits 1 and 2: u << m >= v0
 * when u >= ceil(v0 / 2^m), and the child's last cell is <= v1 when n - 1 <= v1 or u < (v1 + 1) >> m. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_cube_axis(bhcl_u32 U, bhcl_u32 m, bhcl_u32 v0, bhcl_u32 v1, bhcl_u32 n) {
  const bhcl_u32 lo = (v0 + (1u << m) - 1u) >> m;
  const bhcl_u32 hi = v1 >= n - 1u ? 0xffffffffu : (v1 + 1u) >> m;
  const bhcl_u32 u = 2u * U;
  return (u >= lo && u < hi ? 1u : 0u) | (u + 1u >= lo && u + 1u < hi ? 2u : 0u);
}

/* The children o of node (X, Y, Z) of level m + 1 that the rings have searched all of (those for
 * which bhcl_grid_walk_child returns -1), as bits o: the best-first walk's cube test, once per
 * node instead of once per child (most nodes miss the cube, and cost the first test alone). */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_cube_children(const bhcl_grid_walk_ctx* w, bhcl_u32 m, bhcl_u32 X, bhcl_u32 Y,
                                                  bhcl_u32 Z) {
  const bhcl_u32 l = m + 1u; /* a node that misses the cube has no child inside it */
  if (X < (w->vx0 >> l) || X > (w->vx1 >> l) || Y < (w->vy0 >> l) || Y > (w->vy1 >> l) || Z < (w->vz0 >> l) ||
      Z > (w->vz1 >> l))
    return 0u;
  const bhcl_u32 ax = bhcl_grid_cube_axis(X, m, w->vx0, w->vx1, w->g.nx);
  const bhcl_u32 ay = bhcl_grid_cube_axis(Y, m, w->vy0, w->vy1, w->g.ny);
  const bhcl_u32 az = bhcl_grid_cube_axis(Z, m, w->vz0, w->vz1, w->g.nz);
  return ((ax & 1u) * 0x55u | (ax >> 1) * 0xaau) & ((ay & 1u) * 0x33u | (ay >> 1) * 0xccu) &
         ((az & 1u) * 0x0fu | (az >> 1) * 0xf0u);
}

/* Scans fine cell (x, y, z) (a level-0 child of the walk). Returns 0 when the budget stops it. */
#define BHCL_GRID_WALK_CELL(x_, y_, z_)                                   \
  {                                                                       \
    if (examined >= budget) return examined;                              \
    const bhcl_u32 c_ = ((z_) * w->g.ny + (y_)) * w->g.nx + (x_);         \
    const bhcl_u32 a_ = bhcl_grid_start(starts, w->g.sparse, c_);         \
    const bhcl_u32 b_ = bhcl_grid_start(starts, w->g.sparse, c_ + 1u);    \
    BHCL_GRID_SCAN_WALK(st, a_, b_);                                      \
    examined += b_ - a_;                                                  \
  }

/* Entering node (X, Y, Z) of level l, whose level starts at byte off: *near, its child on the
 * query's side, and (returned) its children holding points by visiting position. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_walk_enter(BHCL_GLOBAL const bhcl_u8* occ, const bhcl_grid_walk_ctx* w,
                                               bhcl_u32 off, bhcl_u32 l, bhcl_u32 X, bhcl_u32 Y, bhcl_u32 Z,
                                               bhcl_u32* near) {
  *near = bhcl_grid_occ_near(w->cx, w->cy, w->cz, X, Y, Z, l - 1u);
  return bhcl_grid_occ_pending(occ[bhcl_grid_occ_index(w->g, off, l, X, Y, Z)], *near);
}

/* The cells of row (y, z) among x = x0 + i (i < 4) that the block's level-1 bytes l1[] (by
 * (x, y, z) half: bx | by << 1 | bz << 2) show occupied, as bits i. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_block_row_bits(const bhcl_u32* l1, bhcl_u32 y, bhcl_u32 z) {
  const bhcl_u32 node = ((y >> 1) & 1u) << 1 | ((z >> 1) & 1u) << 2; /* the level-1 node's by, bz */
  const bhcl_u32 bit = (y & 1u) << 1 | (z & 1u) << 2;                 /* the cell's within it */
  const bhcl_u32 lo = l1[node] >> bit, hi = l1[node | 1u] >> bit;    /* x halves 0 and 1 */
  return (lo & 1u) | ((lo >> 1) & 1u) << 1 | (hi & 1u) << 2 | ((hi >> 1) & 1u) << 3;
}

/* The 4 cells c0..c0 + 3 of an axis nearest first from the query's cell c, as nibbles: the i-th
 * is c0 + ((order >> 4 i) & 15). */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_block_order(bhcl_u32 c, bhcl_u32 c0) {
  if (c <= c0) return 0x3210u;
  if (c == c0 + 1u) return 0x3201u;
  if (c == c0 + 2u) return 0x0132u;
  return 0x0123u;
}

/* Level-2 node (X, Y, Z) (4^3 fine cells) scanned by its rows: for each row whose slabs (clipped
 * to the node's points' box) come within the bound and whose cells the level-1 bytes show
 * occupied, the occupied cells' span clipped by the bound at both ends, less the rings' cube, as
 * one run (or two where the cube cuts it). Each bound summed in a point's distance's order
 * ((x^2 + y^2) + z^2; a row's with x^2 = 0), so that it stays below every point's to the bit. Why: far from the points the walk met a node's level-1
 * children and fine cells one test each (two clusters, k = 10: 23 level-1 and 34 fine-cell tests a
 * query, the cells about one point each), where a row is 4 cells in one run: here the node's four
 * slabs of each axis are computed once (the x ones too: at each row's ends they had been 4 % of
 * the instructions at k = 10 and 6 % at k = 50, two clusters), a row costs a sum of them, and its
 * cells one run. Every point within the bound
 * outside the cube is scanned once, as the child walk would. Returns the points examined. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_walk_block(BHCL_GLOBAL const bhcl_u32* starts, BHCL_GLOBAL const float* px,
                                               BHCL_GLOBAL const float* py, BHCL_GLOBAL const float* pz,
                                               BHCL_GLOBAL const bhcl_i32* pid, BHCL_GLOBAL const bhcl_u8* occ,
                                               const bhcl_grid_walk_ctx* w, bhcl_u32 X, bhcl_u32 Y, bhcl_u32 Z,
                                               bhcl_u32 examined, bhcl_u32 budget, BHCL_GRID_STATE* st) {
  const float qx = w->qx, qy = w->qy, qz = w->qz;
  const bhcl_grid_geom g = w->g;
  const bhcl_grid_dbox b = w->tboff ? bhcl_grid_walk_box2(w, X, Y, Z) : w->db;
  const bhcl_u32 x0 = X << 2, y0 = Y << 2, z0 = Z << 2;
  const bhcl_u32 d1x = bhcl_grid_occ_dim(g.nx, 1u), d1y = bhcl_grid_occ_dim(g.ny, 1u), d1z = bhcl_grid_occ_dim(g.nz, 1u);
  /* The level-1 children's bytes (0 outside the grid), an x pair from one index (x is fastest
   * in the level's bytes; the first of a pair is inside, as the node is), and the rows they show
   * occupied as one mask: rm bit (y - y0) + 4 (z - z0). */
  bhcl_u32 l1[8], rm = 0u;
  const bhcl_u32 i1 = bhcl_grid_occ_index(g, 0u, 1u, 2u * X, 2u * Y, 2u * Z);
  const bhcl_u32 x1in = 2u * X + 1u < d1x;
  for (bhcl_u32 o = 0; o < 8u; o += 2u) {
    const bhcl_u32 oy = (o >> 1) & 1u, oz = o >> 2;
    const bhcl_u32 in = 2u * Y + oy < d1y && 2u * Z + oz < d1z;
    const bhcl_u32 i = i1 + (oz * d1y + oy) * d1x;
    l1[o] = in ? occ[i] : 0u;
    l1[o + 1u] = in && x1in ? occ[i + 1u] : 0u;
    /* r = c | c >> 1: bits 0, 2, 4, 6 the rows (y & 1, z & 1) = (0, 0), (1, 0), (0, 1), (1, 1) */
    const bhcl_u32 c = l1[o] | l1[o + 1u], r = c | (c >> 1);
    rm |= ((r & 1u) | ((r >> 1) & 2u) | (r & 16u) | ((r >> 1) & 32u)) << (2u * oy + 8u * oz);
  }
  float ey2[4], ex2[4];
  for (bhcl_u32 j = 0; j < 4u; ++j) {
    const float e = bhcl_grid_slabs_in(qy, g.oy, g.h, g.margin, y0 + j, y0 + j, b.ly, b.hy);
    ey2[j] = e * e;
    const float f = bhcl_grid_slabs_in(qx, g.ox, g.h, g.margin, x0 + j, x0 + j, b.lx, b.hx);
    ex2[j] = f * f;
  }
  /* Rows nearest first along z, then y (the bound tightens before the far rows), stepping from
   * occupied row to occupied row (none outside the grid; most planes of a sparse node have none):
   * rv, the occupied rows by visiting position (bit jj + 4 (z - z0) for row y0 + ((oy >> 4 jj) & 15)),
   * zv the planes holding one (bit i for plane z0 + ((oz >> 4 i) & 15)). Why: the rows' and planes'
   * bits from the level-1 bytes had been computed at each of the 16 rows and 4 planes, where a
   * node far from the points has about 5 and 2.5 occupied; host reference, two clusters, k = 10:
   * -2.6 % of the instructions (the mask -1.1 %, the steps by bits -0.7 % and -0.8 %). */
  const bhcl_u32 oz = bhcl_grid_block_order(w->cz, z0), oy = bhcl_grid_block_order(w->cy, y0);
  bhcl_u32 rv = 0u, zv = 0u;
  for (bhcl_u32 jj = 0; jj < 4u; ++jj) rv |= ((rm >> ((oy >> (4u * jj)) & 15u)) & 0x1111u) << jj;
  const bhcl_u32 ne = (rm | (rm >> 1) | (rm >> 2) | (rm >> 3)) & 0x1111u; /* bit 4 (z - z0): a row of z */
  for (bhcl_u32 i = 0; i < 4u; ++i) zv |= ((ne >> (4u * ((oz >> (4u * i)) & 15u))) & 1u) << i;
  for (; zv != 0u; zv &= zv - 1u) {
    const bhcl_u32 zl = (oz >> (4u * BHCL_GRID_CTZ(zv))) & 15u, z = z0 + zl;
    const float ez = bhcl_grid_slabs_in(qz, g.oz, g.h, g.margin, z, z, b.lz, b.hz);
    const float ez2 = ez * ez;
    if (ez2 > BHCL_GRID_BOUND(st)) continue;
    for (bhcl_u32 pv = (rv >> (4u * zl)) & 15u; pv != 0u; pv &= pv - 1u) {
      const bhcl_u32 j = (oy >> (4u * BHCL_GRID_CTZ(pv))) & 15u, y = y0 + j;
      if (ey2[j] + ez2 > BHCL_GRID_BOUND(st)) continue;
      bhcl_u32 bits = bhcl_grid_block_row_bits(l1, y, z);
      bhcl_u32 xa = x0 + BHCL_GRID_CTZ(bits), xb = x0 + (31u - BHCL_GRID_CLZ(bits));
      while (xa <= xb) { /* the row's ends, clipped by the bound (the cells between are scanned) */
        if ((ex2[xa - x0] + ey2[j]) + ez2 <= BHCL_GRID_BOUND(st)) break; /* a point's sum's order */
        ++xa;
      }
      while (xb > xa) {
        if ((ex2[xb - x0] + ey2[j]) + ez2 <= BHCL_GRID_BOUND(st)) break;
        --xb;
      }
      if (xa > xb) continue;
      const bhcl_u32 row = (z * g.ny + y) * g.nx;
      /* The rings' cube: cells vx0..vx1 of this row are theirs. */
      const int in_cube = y >= w->vy0 && y <= w->vy1 && z >= w->vz0 && z <= w->vz1 && w->vx0 <= w->vx1 &&
                          xa <= w->vx1 && xb >= w->vx0;
      for (bhcl_u32 part = 0; part < 2u; ++part) {
        bhcl_u32 ra = xa, rb = xb; /* part 0: the run before the cube (or all of it), 1: after */
        if (in_cube) {
          if (part == 0u) {
            if (xa >= w->vx0) continue;
            rb = w->vx0 - 1u;
          } else {
            if (xb <= w->vx1) continue;
            ra = w->vx1 + 1u;
          }
        } else if (part == 1u) {
          break;
        }
        if (examined >= budget) return examined;
        const bhcl_u32 a = bhcl_grid_start(starts, g.sparse, row + ra);
        const bhcl_u32 e = bhcl_grid_start(starts, g.sparse, row + rb + 1u);
        BHCL_GRID_SCAN_WALK(st, a, e);
        examined += e - a;
      }
    }
  }
  return examined;
}

/* Every fine cell below node (X0, Y0, Z0) of level l0 (whose level starts at byte off) outside the
 * rings' cube that the pyramid shows occupied and whose slabs come within the bound, found
 * depth-first, the children of a node in BHCL_GRID_OCC_ORDER and each tested against the bound as
 * it is met (a node of empty space costs one bit test, however large). Stackless: on the way up, a
 * child's position in its parent's order is recomputed from its coordinates. Returns the points
 * examined (`examined` on entry: those before). */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_walk_depth_first(BHCL_GLOBAL const bhcl_u32* starts,
                                                     BHCL_GLOBAL const float* px, BHCL_GLOBAL const float* py,
                                                     BHCL_GLOBAL const float* pz, BHCL_GLOBAL const bhcl_i32* pid,
                                                     BHCL_GLOBAL const bhcl_u8* occ, const bhcl_grid_walk_ctx* w,
                                                     bhcl_u32 l0, bhcl_u32 X0, bhcl_u32 Y0, bhcl_u32 Z0, bhcl_u32 off,
                                                     bhcl_u32 examined, bhcl_u32 budget, BHCL_GRID_STATE* st) {
  const float qx = w->qx, qy = w->qy, qz = w->qz;
  bhcl_u32 l = l0, X = X0, Y = Y0, Z = Z0;
  /* A level-2 node to scan by its rows (w->rows): the walk's start itself (then the walk is that
   * node alone), or a child met. One call of bhcl_grid_walk_block for both: each inlined copy
   * of it is a large part of the kernel's compile time. */
  const bhcl_u32 whole = w->rows && l0 == 2u;
  bhcl_u32 block = whole, bx = X0, by = Y0, bz = Z0;
  /* Per node, read once on entering it (and again on coming back up to it): the child on the
   * query's side and, as bits by visiting position, its children that hold points still to be
   * visited; below level 3, the level-2 ancestor's box its children clip to. */
  bhcl_u32 near = 0u;
  bhcl_u32 pend = whole ? 0u : bhcl_grid_walk_enter(occ, w, off, l, X, Y, Z, &near);
  bhcl_grid_dbox b2 = w->db; /* (a walk that is one block: the block reads its box itself) */
  if (BHCL_GRID_KEEP_BOX2 && w->tboff && l <= 2u && !whole)
    b2 = bhcl_grid_walk_box2(w, X >> (2u - l), Y >> (2u - l), Z >> (2u - l));
  for (;;) {
    if (block) {
      block = 0u;
      examined = bhcl_grid_walk_block(starts, px, py, pz, pid, occ, w, bx, by, bz, examined, budget, st);
      if (whole || examined >= budget) return examined;
      continue;
    }
    if (pend == 0u) { /* this node is done: up to its parent, at the position after it */
      if (l == l0) break;
      const bhcl_u32 o = (X & 1u) | ((Y & 1u) << 1) | ((Z & 1u) << 2);
      off += bhcl_grid_occ_size(w->g, l);
      ++l;
      X >>= 1;
      Y >>= 1;
      Z >>= 1;
      pend = bhcl_grid_walk_enter(occ, w, off, l, X, Y, Z, &near);
      pend &= ~((2u << BHCL_GRID_OCC_ORDER(o ^ near)) - 1u); /* the children after the one done */
      continue;
    }
    const bhcl_u32 o = BHCL_GRID_OCC_ORDER(BHCL_GRID_CTZ(pend)) ^ near;
    pend &= pend - 1u;
    const bhcl_u32 m = l - 1u; /* the child's level */
    bhcl_u32 ux, uy, uz;
    const bhcl_u32 moff = m >= 2u ? off - bhcl_grid_occ_size(w->g, m) : 0u;
    const float d = bhcl_grid_walk_child(w, m, moff, X, Y, Z, o, &ux, &uy, &uz, BHCL_GRID_KEEP_BOX2 ? &b2 : 0);
    if (d < 0.0f || d > BHCL_GRID_BOUND(st)) continue;
    if (m == 0u) { /* a fine cell: its run */
      BHCL_GRID_WALK_CELL(ux, uy, uz)
      continue;
    }
    if (w->rows && m == 2u) { /* a level-2 node: by its rows, at the loop's top */
      block = 1u, bx = ux, by = uy, bz = uz;
      continue;
    }
    off -= bhcl_grid_occ_size(w->g, m);
    l = m;
    X = ux;
    Y = uy;
    Z = uz;
    pend = bhcl_grid_walk_enter(occ, w, off, l, X, Y, Z, &near);
    if (BHCL_GRID_KEEP_BOX2 && w->tboff && l == 2u) b2 = bhcl_grid_walk_box2(w, X, Y, Z);
  }
  return examined;
}

/* The best-first walk's queue: pyramid nodes by level and coordinates, in descending squared
 * distance from the query (the nearest is popped from the back; of equal distances the last
 * queued). The order is kept on one 64-bit key per entry, the distance's bits (a distance is
 * >= +0, so its bits order as it does) above the slot of the node's fields, which stay where
 * they were written (the slots freed by pops are reused). Why: a query between two clusters
 * (k = 10) queues 25 nodes and pops 8, each queued one moving 4 nearer ones, which had moved
 * five arrays each; host reference: -2.6 % of the instructions at k = 10, -1.4 % at k = 50 (an
 * unsorted queue searched at each pop: -1.7 % / +0.8 %). */
#ifndef BHCL_GRID_WALKBUF
#define BHCL_GRID_WALKBUF 32
#endif
/* Nodes of this level or below (4^3 fine cells) are walked depth-first when popped, not expanded
 * into the queue: near the fine cells the depth-first child order is as good and costs no queue
 * moves. A constant, not a define: the host reference must walk the same way. */
#ifndef BHCL_GRID_WALK_DF_LEVEL
#define BHCL_GRID_WALK_DF_LEVEL 2u
#endif
#ifndef BHCL_GRID_WALK_DESCEND
#define BHCL_GRID_WALK_DESCEND 1
#endif
/* 1: the best-first forms scan a level-2 node by its rows (bhcl_grid_walk_block); 0: child by
 * child, as the GPU form (an experiment: the same rows; the host reference follows 1). */
#ifndef BHCL_GRID_BLOCK_ROWS
#define BHCL_GRID_BLOCK_ROWS 1
#endif
#ifdef __OPENCL_C_VERSION__
#define BHCL_GRID_FBITS(f) as_uint(f)
#define BHCL_GRID_BITSF(u) as_float(u)
#else
inline bhcl_u32 bhcl_grid_fbits(float f) { bhcl_u32 u; std::memcpy(&u, &f, 4); return u; }
inline float bhcl_grid_bitsf(bhcl_u32 u) { float f; std::memcpy(&f, &u, 4); return f; }
#define BHCL_GRID_FBITS(f) bhcl_grid_fbits(f)
#define BHCL_GRID_BITSF(u) bhcl_grid_bitsf(u)
#endif
typedef struct bhcl_grid_walk_queue {
  bhcl_u64 key[BHCL_GRID_WALKBUF]; /* the distance's bits << 32 | the slot of the node's fields */
  bhcl_u32 xl[BHCL_GRID_WALKBUF]; /* by slot: X | level << 27 */
  bhcl_u32 y[BHCL_GRID_WALKBUF], z[BHCL_GRID_WALKBUF];
  bhcl_u32 off[BHCL_GRID_WALKBUF]; /* the byte of the node's level */
} bhcl_grid_walk_queue;

/* The search past the first rings: every fine cell outside the cube of cells [c - r0, c + r0]
 * around the home cell c (which the rings have accounted for) that the pyramid shows occupied and
 * whose slabs come within the bound. walk_cap 0: depth-first from the top
 * (bhcl_grid_walk_depth_first; no private queue, the GPU form). walk_cap > 0 (<= BHCL_GRID_WALKBUF):
 * best-first, the nearest node of a queue of walk_cap popped first and followed down into its
 * nearest child level by level (its other children queued), its fine cells scanned as met, so
 * that the first points found are near and the bound tightens before the far nodes are reached (a
 * query between two clusters no longer scans the far one first; one over a surface no longer
 * expands every coarse node nearer than the surface before it reaches a point); a child that
 * finds the queue full is walked depth-first at once. Either order visits every node within the
 * final bound, so the rows are the same. Returns the points examined (`examined` on entry: the
 * rings'). */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_search_far(BHCL_GLOBAL const bhcl_u32* starts,
                                               BHCL_GLOBAL const float* px, BHCL_GLOBAL const float* py,
                                               BHCL_GLOBAL const float* pz, BHCL_GLOBAL const bhcl_i32* pid,
                                               BHCL_GLOBAL const bhcl_u8* occ, const bhcl_grid_geom g,
                                               const bhcl_grid_dbox db, float qx, float qy, float qz, bhcl_u32 cx, bhcl_u32 cy,
                                               bhcl_u32 cz, bhcl_u32 r0, bhcl_u32 examined,
                                               bhcl_u32 budget, bhcl_u32 walk_cap, bhcl_u32 kth, BHCL_GRID_STATE* st) {
  bhcl_u32 top_off, total;
  const bhcl_u32 top = bhcl_grid_occ_top(g, &top_off, &total);
  bhcl_grid_walk_ctx wc;
  bhcl_grid_walk_ctx* w = &wc;
  wc.g = g;
  wc.db = db;
  wc.qx = qx;
  wc.qy = qy;
  wc.qz = qz;
  wc.cx = cx;
  wc.cy = cy;
  wc.cz = cz;
  /* r0 0xffffffff: no ring was searched (the cube is empty) */
  wc.vx0 = r0 == 0xffffffffu ? 1u : cx > r0 ? cx - r0 : 0u;
  wc.vy0 = cy > r0 ? cy - r0 : 0u;
  wc.vz0 = cz > r0 ? cz - r0 : 0u;
  wc.vx1 = r0 == 0xffffffffu ? 0u : cx + r0;
  wc.vy1 = cy + r0;
  wc.vz1 = cz + r0;
  wc.occ = occ;
  wc.size1 = bhcl_grid_occ_size(g, 1u);
  wc.tboff = BHCL_GRID_TBOX && top >= 2u ? bhcl_grid_tbox_off(total) : 0u;
  /* Level-2 nodes by their rows in the best-first forms (CPU devices; the GPU form keeps its
   * registers and walks their children), for k >= 2: at k = 1 the bound is one point's from the
   * first point on, and the cells' own tests prune more than a row's ends (two clusters: 4209
   * points examined by rows against 3202 child by child, 2000 queries). */
  wc.rows = BHCL_GRID_BLOCK_ROWS && walk_cap != 0u && top >= 2u && kth >= 2u ? 1u : 0u;
  /* The queue keeps a node's x in 27 bits (the level in the other 5). */
  if (walk_cap == 0u || g.nx > 0x07ffffffu)
    return bhcl_grid_walk_depth_first(starts, px, py, pz, pid, occ, w, top, 0u, 0u, 0u, top_off, examined, budget, st);
  bhcl_grid_walk_queue qu;
  bhcl_u32 nq = 1u;
  bhcl_u32 hw = 1u, nf = 0u; /* the slots written so far; the free ones among them, fs[0, nf) */
  bhcl_u8 fs[BHCL_GRID_WALKBUF];
  qu.key[0] = 0u; /* distance +0, slot 0 */
  qu.xl[0] = top << 27;
  qu.y[0] = qu.z[0] = 0u;
  qu.off[0] = top_off;
  while (nq > 0u) {
    --nq;
    if (BHCL_GRID_BITSF((bhcl_u32)(qu.key[nq] >> 32)) > BHCL_GRID_BOUND(st)) break; /* the rest are farther still */
    const bhcl_u32 t = (bhcl_u32)qu.key[nq] & 0xffu; /* its slot, free again */
    fs[nf++] = (bhcl_u8)t;
    bhcl_u32 l = qu.xl[t] >> 27, X = qu.xl[t] & 0x07ffffffu, Y = qu.y[t], Z = qu.z[t];
    bhcl_u32 off = qu.off[t];
    /* Down from the popped node, BHCL_GRID_WALK_DESCEND: always into its nearest child, the others
     * queued, so that the first fine cells are reached (and the bound made) after one descent, not
     * after every coarse node nearer than them has been expanded; the queue then prunes. */
    for (;;) {
      if (l <= BHCL_GRID_WALK_DF_LEVEL) {
        examined = bhcl_grid_walk_depth_first(starts, px, py, pz, pid, occ, w, l, X, Y, Z, off, examined, budget, st);
        if (examined >= budget) return examined;
        break;
      }
      const bhcl_u32 m = l - 1u, moff = off - bhcl_grid_occ_size(g, m);
      /* The children (of level m >= 2) are tested here, not by bhcl_grid_walk_child: the rings'
       * cube once for all eight (bhcl_grid_cube_children), and each child's box (with the boxes,
       * always but in the BHCL_GRID_TBOX 0 experiment) from the node's first child's index, the
       * level's dimensions read once. The same distances. Why: the per-child form recomputed the
       * child's cell span, its clamps, the cube test and the level's dimensions, 105 instructions
       * a child (two clusters, k = 10: 44 child tests a query, 21 % of the instructions); host
       * reference -12.2 % of the instructions at k = 10, -5.9 % at k = 50. */
      const bhcl_u32 mask = occ[bhcl_grid_occ_index(g, off, l, X, Y, Z)] & ~bhcl_grid_cube_children(w, m, X, Y, Z);
      const bhcl_u32 dxm = bhcl_grid_occ_dim(g.nx, m), dxym = dxm * bhcl_grid_occ_dim(g.ny, m);
      const bhcl_u32 box0 = moff - w->size1 + 2u * Z * dxym + 2u * Y * dxm + 2u * X; /* child 0's box */
      float nd = -1.0f; /* the nearest child so far (-1: none), kept out of the queue */
      bhcl_u32 nx_ = 0u, ny_ = 0u, nz_ = 0u;
      for (bhcl_u32 bits = mask; bits != 0u; bits &= bits - 1u) { /* the children holding points */
        const bhcl_u32 o = BHCL_GRID_CTZ(bits);
        bhcl_u32 ux = 2u * X + (o & 1u), uy = 2u * Y + ((o >> 1) & 1u), uz = 2u * Z + (o >> 2);
        float d = w->tboff ? bhcl_grid_box_dist(w, bhcl_grid_tbox_load(occ, w->tboff,
                                                                       box0 + (o & 1u) + ((o >> 1) & 1u) * dxm + (o >> 2) * dxym))
                           : bhcl_grid_walk_child(w, m, moff, X, Y, Z, o, &ux, &uy, &uz, 0);
        if (d < 0.0f || d > BHCL_GRID_BOUND(st)) continue;
        if (BHCL_GRID_WALK_DESCEND && (nd < 0.0f || d < nd)) { /* the new nearest: queue the old one */
          const float td = nd;
          const bhcl_u32 tx = nx_, ty = ny_, tz = nz_;
          nd = d, nx_ = ux, ny_ = uy, nz_ = uz;
          if (td < 0.0f) continue;
          d = td, ux = tx, uy = ty, uz = tz;
        }
        if (nq < walk_cap) { /* m >= BHCL_GRID_WALK_DF_LEVEL: never a fine cell */
          /* above the farther and the equal ones (popped before them), below the nearer (kb's
           * low bits 0: a key of equal distance is >= kb) */
          bhcl_u32 j = nq++;
          const bhcl_u64 kb = (bhcl_u64)BHCL_GRID_FBITS(d) << 32;
          while (j > 0u && qu.key[j - 1u] < kb) {
            qu.key[j] = qu.key[j - 1u];
            --j;
          }
          const bhcl_u32 sl = nf > 0u ? fs[--nf] : hw++; /* < walk_cap: nq - 1 slots are taken */
          qu.key[j] = kb | sl;
          j = sl;
          qu.xl[j] = ux | (m << 27);
          qu.y[j] = uy;
          qu.z[j] = uz;
          qu.off[j] = moff;
        } else {
          examined = bhcl_grid_walk_depth_first(starts, px, py, pz, pid, occ, w, m, ux, uy, uz, moff, examined, budget, st);
          if (examined >= budget) return examined;
        }
      }
      if (nd < 0.0f || nd > BHCL_GRID_BOUND(st)) break;
      l = m, X = nx_, Y = ny_, Z = nz_, off = moff;
    }
  }
  return examined;
}
#undef BHCL_GRID_WALK_CELL

/* fine_rings: the rings searched before the pyramid walk takes over (0xffffffff: rings only).
 * kth: the list's k (0 for the radius search), which picks how the walk scans a level-2 node. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_search(BHCL_GLOBAL const bhcl_u32* starts,
                                           BHCL_GLOBAL const float* px, BHCL_GLOBAL const float* py,
                                           BHCL_GLOBAL const float* pz, BHCL_GLOBAL const bhcl_i32* pid,
                                           BHCL_GLOBAL const bhcl_u8* occ, const bhcl_grid_geom g,
                                           const bhcl_grid_dbox db, float qx, float qy, float qz,
                                           bhcl_u32 budget, bhcl_u32 cap,
                                           bhcl_u32 fine_rings, bhcl_u32 walk_cap, bhcl_u32 kth, BHCL_GRID_STATE* st) {
  const bhcl_u32 cx = bhcl_grid_cell(qx, g.ox, g.inv_h, g.nx);
  const bhcl_u32 cy = bhcl_grid_cell(qy, g.oy, g.inv_h, g.ny);
  const bhcl_u32 cz = bhcl_grid_cell(qz, g.oz, g.inv_h, g.nz);
  bhcl_u32 rmax = cx > g.nx - 1u - cx ? cx : g.nx - 1u - cx;
  bhcl_u32 t = cy > g.ny - 1u - cy ? cy : g.ny - 1u - cy;
  rmax = rmax > t ? rmax : t;
  t = cz > g.nz - 1u - cz ? cz : g.nz - 1u - cz;
  rmax = rmax > t ? rmax : t;
  bhcl_u32 examined = 0;
  /* The walk, where one is taken, starts from one call below the rings (one copy of its scan in
   * the inlined search, not one per way into it): walk_r0 is the last ring searched
   * (0xffffffff: none), kNoWalk while the rings answer alone. */
  const bhcl_u32 kNoWalk = 0xfffffffeu;
  bhcl_u32 walk_r0 = kNoWalk;
  /* BHCL_GRID_HOME_SKIP 1: no point within the home cell's 4^3 block of the pyramid's level 2
   * (nor, then, within a ring of it in most cases): the walk alone, the rings would only look up
   * empty rows. */
  if (BHCL_GRID_HOME_SKIP == 1 && fine_rings != 0xffffffffu && rmax > fine_rings &&
      bhcl_grid_occ_size(g, 1u) > 1u) { /* level 2 exists */
    if (occ[bhcl_grid_occ_index(g, bhcl_grid_occ_size(g, 1u), 2u, cx >> 2, cy >> 2, cz >> 2)] == 0u)
      walk_r0 = 0xffffffffu;
  }
  bhcl_grid_rows rows;
#if BHCL_GRID_NEAR > 0
  /* n?[o + BHCL_GRID_NEAR]: the squared slab distance of cell c? + o (filled at ring |o|, inside
   * the grid only: the rows skip the others before they read them) */
  float nx2[2 * BHCL_GRID_NEAR + 1], ny2[2 * BHCL_GRID_NEAR + 1], nz2[2 * BHCL_GRID_NEAR + 1];
#define BHCL_GRID_SQ(arr, o, t, o0, c)                                                       \
  (((o) >= -BHCL_GRID_NEAR && (o) <= BHCL_GRID_NEAR) ? arr[(o) + BHCL_GRID_NEAR]             \
                                                     : bhcl_grid_sq(bhcl_grid_slab(t, o0, g.h, g.margin, (bhcl_u32)(c))))
#else
#define BHCL_GRID_SQ(arr, o, t, o0, c) bhcl_grid_sq(bhcl_grid_slab(t, o0, g.h, g.margin, (bhcl_u32)(c)))
#endif
  for (bhcl_u32 r = 0; walk_r0 == kNoWalk && r <= rmax; ++r) {
    const int side = 2 * (int)r + 1;
    bhcl_u32 nr = 0;
#if BHCL_GRID_NEAR > 0
    if (r <= BHCL_GRID_NEAR) {
      const int N = BHCL_GRID_NEAR, ir = (int)r;
      if (cx >= r) nx2[N - ir] = bhcl_grid_sq(bhcl_grid_slab(qx, g.ox, g.h, g.margin, cx - r));
      if (cx + r < g.nx) nx2[N + ir] = bhcl_grid_sq(bhcl_grid_slab(qx, g.ox, g.h, g.margin, cx + r));
      if (cy >= r) ny2[N - ir] = bhcl_grid_sq(bhcl_grid_slab(qy, g.oy, g.h, g.margin, cy - r));
      if (cy + r < g.ny) ny2[N + ir] = bhcl_grid_sq(bhcl_grid_slab(qy, g.oy, g.h, g.margin, cy + r));
      if (cz >= r) nz2[N - ir] = bhcl_grid_sq(bhcl_grid_slab(qz, g.oz, g.h, g.margin, cz - r));
      if (cz + r < g.nz) nz2[N + ir] = bhcl_grid_sq(bhcl_grid_slab(qz, g.oz, g.h, g.margin, cz + r));
    }
#endif
    for (int jz = 0; jz < side; ++jz) {
      const int oz = bhcl_grid_offset(jz);
      const int z = (int)cz + oz;
      if (z < 0 || z >= (int)g.nz) continue;
      const float ez2 = BHCL_GRID_SQ(nz2, oz, qz, g.oz, z);
      for (int jy = 0; jy < side; ++jy) {
        const int oy = bhcl_grid_offset(jy);
        const int y = (int)cy + oy;
        if (y < 0 || y >= (int)g.ny) continue;
        const float syz = BHCL_GRID_SQ(ny2, oy, qy, g.oy, y) + ez2;
        const float bound = BHCL_GRID_BOUND(st);
        if (syz > bound) continue;
        const bhcl_u32 row = ((bhcl_u32)z * g.ny + (bhcl_u32)y) * g.nx;
        const int ay = oy < 0 ? -oy : oy, az = oz < 0 ? -oz : oz;
        if ((bhcl_u32)(ay > az ? ay : az) == r) {
          /* A whole row of the ring: cells cx - r .. cx + r, clipped by the bound. */
          int xa = (int)cx - (int)r, xb = (int)cx + (int)r;
          if (xa < 0) xa = 0;
          if (xb > (int)g.nx - 1) xb = (int)g.nx - 1;
          while (xa <= xb) {
            if (BHCL_GRID_SQ(nx2, xa - (int)cx, qx, g.ox, xa) + syz <= bound) break;
            ++xa;
          }
          while (xb > xa) {
            if (BHCL_GRID_SQ(nx2, xb - (int)cx, qx, g.ox, xb) + syz <= bound) break;
            --xb;
          }
          if (xa > xb) continue;
          const bhcl_u32 a = bhcl_grid_start(starts, g.sparse, row + (bhcl_u32)xa);
          const bhcl_u32 b = bhcl_grid_start(starts, g.sparse, row + (bhcl_u32)xb + 1u);
          BHCL_GRID_RUN(syz, a, b)
        } else {
          /* An inner row: only its two end cells belong to the ring. */
          for (int e = 0; e < 2; ++e) {
            const int x = e == 0 ? (int)cx - (int)r : (int)cx + (int)r;
            if (x < 0 || x >= (int)g.nx) continue;
            const float d = BHCL_GRID_SQ(nx2, x - (int)cx, qx, g.ox, x) + syz;
            if (d > bound) continue;
            const bhcl_u32 a = bhcl_grid_start(starts, g.sparse, row + (bhcl_u32)x);
            const bhcl_u32 b = bhcl_grid_start(starts, g.sparse, row + (bhcl_u32)x + 1u);
            BHCL_GRID_RUN(d, a, b)
          }
        }
      }
    }
    /* The gathered runs, nearest first, while within the bound. */
    for (bhcl_u32 i = 0; i < nr; ++i) {
      if (rows.d[i] > BHCL_GRID_BOUND(st)) break;
      if (examined >= budget) return examined;
      BHCL_GRID_SCAN(st, rows.a[i], rows.b[i]);
      examined += rows.b[i] - rows.a[i];
    }
    /* Exact stop: nothing outside the rings visited is within the bound. */
    float w = bhcl_grid_reach(qx, g.ox, g.h, g.margin, cx, r, g.nx);
    w = BHCL_FMIN(w, bhcl_grid_reach(qy, g.oy, g.h, g.margin, cy, r, g.ny));
    w = BHCL_FMIN(w, bhcl_grid_reach(qz, g.oz, g.h, g.margin, cz, r, g.nz));
    if (w > 0.0f && BHCL_GRID_BOUND(st) < w * w) return examined;
    /* BHCL_GRID_HOME_SKIP 2: the same test after ring 0, for a query whose home cell was empty. */
    if (BHCL_GRID_HOME_SKIP == 2 && r == 0u && examined == 0u && fine_rings != 0xffffffffu && rmax > fine_rings &&
        bhcl_grid_occ_size(g, 1u) > 1u &&
        occ[bhcl_grid_occ_index(g, bhcl_grid_occ_size(g, 1u), 2u, cx >> 2, cy >> 2, cz >> 2)] == 0u)
      walk_r0 = 0u;
    /* Past fine_rings, the rings go on only while the stop is near (the bound within
     * BHCL_GRID_RING_SLACK more rings' reach, at most BHCL_GRID_RING_CAP rings past fine_rings):
     * a query among the points at a large k keeps its nearest-first rings, one far from them (no
     * bound yet, or a large radius) goes to the walk. */
    if (fine_rings != 0xffffffffu && r >= fine_rings && r < rmax) {
      const float reach = w + (float)BHCL_GRID_RING_SLACK * g.h;
      if (!(BHCL_GRID_BOUND(st) < reach * reach) || r >= fine_rings + BHCL_GRID_RING_CAP) walk_r0 = r;
    }
  }
#undef BHCL_GRID_SQ
  if (walk_r0 == kNoWalk) return examined;
  return bhcl_grid_search_far(starts, px, py, pz, pid, occ, g, db, qx, qy, qz, cx, cy, cz, walk_r0, examined, budget,
                              walk_cap, kth, st);
}
#undef BHCL_GRID_RUN
#endif /* BHCL_GRID_STATE */
