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
  bhcl_grid_geom g;
  g.ox = geo0.x;
  g.oy = geo0.y;
  g.oz = geo0.z;
  g.h = geo0.w;
  g.inv_h = geo1.x;
  g.margin = geo1.y;
  g.nx = dims.x;
  g.ny = dims.y;
  g.nz = dims.z;
  g.sparse = dims.w;
  return g;
}
#endif

/* The cell of coordinate t along an axis of n cells from origin o: floor((t - o) / h), clamped. */
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_cell(float t, float o, float inv_h, bhcl_u32 n) {
  float f = (t - o) * inv_h;
  if (!(f > 0.0f)) return 0u;
  if (f >= (float)(n - 1u)) return n - 1u;
  return (bhcl_u32)f;
}

/* Distance from t to the slab of cell i (lowered by the margin, never negative). */
BHCL_GRID_INLINE float bhcl_grid_slab(float t, float o, float h, float margin, bhcl_u32 i) {
  float lo = o + (float)i * h;
  float hi = o + (float)(i + 1u) * h;
  float e = BHCL_FMAX(BHCL_FMAX(lo - t, t - hi), 0.0f) - margin;
  return BHCL_FMAX(e, 0.0f);
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

#endif /* BHCL_GRID_SEARCH_H */

/* The search itself, once per translation unit that defines a state (the geometry above may have
 * been included before without one). */
#if defined(BHCL_GRID_STATE) && !defined(BHCL_GRID_SEARCH_FN)
#define BHCL_GRID_SEARCH_FN
#ifndef BHCL_GRID_ROWBUF
#define BHCL_GRID_ROWBUF 32
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
BHCL_GRID_INLINE bhcl_u32 bhcl_grid_search(BHCL_GLOBAL const bhcl_u32* starts,
                                           BHCL_GLOBAL const float* px, BHCL_GLOBAL const float* py,
                                           BHCL_GLOBAL const float* pz, BHCL_GLOBAL const bhcl_i32* pid,
                                           const bhcl_grid_geom g, float qx, float qy, float qz,
                                           bhcl_u32 budget, bhcl_u32 cap, BHCL_GRID_STATE* st) {
  const bhcl_u32 cx = bhcl_grid_cell(qx, g.ox, g.inv_h, g.nx);
  const bhcl_u32 cy = bhcl_grid_cell(qy, g.oy, g.inv_h, g.ny);
  const bhcl_u32 cz = bhcl_grid_cell(qz, g.oz, g.inv_h, g.nz);
  bhcl_u32 rmax = cx > g.nx - 1u - cx ? cx : g.nx - 1u - cx;
  bhcl_u32 t = cy > g.ny - 1u - cy ? cy : g.ny - 1u - cy;
  rmax = rmax > t ? rmax : t;
  t = cz > g.nz - 1u - cz ? cz : g.nz - 1u - cz;
  rmax = rmax > t ? rmax : t;
  bhcl_u32 examined = 0;
  bhcl_grid_rows rows;
  for (bhcl_u32 r = 0; r <= rmax; ++r) {
    const int side = 2 * (int)r + 1;
    bhcl_u32 nr = 0;
    for (int jz = 0; jz < side; ++jz) {
      const int oz = bhcl_grid_offset(jz);
      const int z = (int)cz + oz;
      if (z < 0 || z >= (int)g.nz) continue;
      const float ez = bhcl_grid_slab(qz, g.oz, g.h, g.margin, (bhcl_u32)z);
      for (int jy = 0; jy < side; ++jy) {
        const int oy = bhcl_grid_offset(jy);
        const int y = (int)cy + oy;
        if (y < 0 || y >= (int)g.ny) continue;
        const float ey = bhcl_grid_slab(qy, g.oy, g.h, g.margin, (bhcl_u32)y);
        const float syz = ey * ey + ez * ez;
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
            float ex = bhcl_grid_slab(qx, g.ox, g.h, g.margin, (bhcl_u32)xa);
            if (ex * ex + syz <= bound) break;
            ++xa;
          }
          while (xb > xa) {
            float ex = bhcl_grid_slab(qx, g.ox, g.h, g.margin, (bhcl_u32)xb);
            if (ex * ex + syz <= bound) break;
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
            const float ex = bhcl_grid_slab(qx, g.ox, g.h, g.margin, (bhcl_u32)x);
            const float d = ex * ex + syz;
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
    if (w > 0.0f && BHCL_GRID_BOUND(st) < w * w) break;
  }
  return examined;
}
#undef BHCL_GRID_RUN
#endif /* BHCL_GRID_STATE */
