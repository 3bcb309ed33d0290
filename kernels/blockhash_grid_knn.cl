/* Block hashing, grid layout (the auto preset): kNN, one work-item per query.
 *
 * The traversal (rings of rows, clipped by the k-th distance, exact stop, budget) is
 * bhcl_grid_search in grid_search.h, shared with the host reference
 * (lib/src/blockhash/grid_query_ref.cpp). This file holds the two forms of the top-k list:
 *  - BHCL_GRID_VTOPK 1 (CPU devices, Quirks::vector_scan): the list in VR float16 + int16
 *    registers, right-aligned (lanes below 16 VR - k hold -inf and never move, so the k-th is
 *    lane 15 of the last register); an insertion is, per register, one shuffle by a lane, two
 *    compares and two selects, no data-dependent loop. A run is scanned 16 points at a time as
 *    float16 distances; only the lanes within the bound are offered. Everything force-inlined,
 *    or clang keeps the list in memory (docs/DESIGN.md, "The grid"). With four registers
 *    the first k candidates are appended unordered and sorted once (BHCL_GRID_FILLSORT).
 *  - BHCL_GRID_VTOPK 0 (GPUs, and k above 64): the sorted list in private arrays, one point at a
 *    time (bhcl_arith.h's insertion).
 * Both keep the k nearest of the same points by (distance, index), so their rows are identical.
 *
 * Defines: BHCL_KMAX (the list's capacity), BHCL_GRID_VTOPK, BHCL_GRID_ROWCAP (the runs of a ring
 * sorted nearest first before they are scanned; 0: none), BHCL_GRID_FILLSORT and
 * BHCL_GRID_SORT_CALL (below), BHCL_GRID_PREFETCH (d > 0: prefetch
 * the home cell of the query d work-items ahead with clang's __builtin_prefetch; PoCL's
 * prefetch() emits nothing). */
#include "knn_common.h"

#ifndef BHCL_GRID_VTOPK
#define BHCL_GRID_VTOPK 0
#endif
#ifndef BHCL_GRID_PREFETCH
#define BHCL_GRID_PREFETCH 0
#endif
#ifndef BHCL_GRID_PREFETCH_DIR /* 1: also the directory entry, 2d ahead */
#define BHCL_GRID_PREFETCH_DIR 1
#endif
#ifndef BHCL_GRID_PREFETCH_RING /* 1: the 9 rows around the home cell, not only the home cell */
#define BHCL_GRID_PREFETCH_RING 1
#endif
/* 1: the ids as well: a run's first line of ids at its start (its points' loads miss at the same
 * time), and the rows' first ids with their points. Without it the first insertion of a run waits
 * for that line alone: 19 % of the kernel's samples at k = 50 on Autzen, random order. */
#ifndef BHCL_GRID_PREFETCH_IDS
#define BHCL_GRID_PREFETCH_IDS 1
#endif
/* The 64-byte lines of each row's first points asked for, per array (16 points a line). */
#ifndef BHCL_GRID_PREFETCH_LINES
#define BHCL_GRID_PREFETCH_LINES 2
#endif

/* The far walk's runs of this many points or fewer are measured one point at a time by the
 * register list's scan (0: every run 16 lanes at a time). */
#ifndef BHCL_GRID_SHORT_RUN
#define BHCL_GRID_SHORT_RUN 4u
#endif

/* The runs of a ring gathered and scanned nearest first (0: scanned as met; grid_search.h). */
#ifndef BHCL_GRID_ROWCAP
#define BHCL_GRID_ROWCAP 0
#endif
#define BHCL_GRID_ROWBUF (BHCL_GRID_ROWCAP > 0 ? BHCL_GRID_ROWCAP : 1)
/* The rings' slab distances within this many cells of the query's kept (grid_search.h): where
 * the form gathers the rings' runs (private arrays allowed), 3. */
#ifndef BHCL_GRID_NEAR
#define BHCL_GRID_NEAR (BHCL_GRID_ROWCAP > 0 ? 3 : 0)
#endif

/* The pyramid nodes the far walk queues, nearest first (0: depth-first, no queue; grid_search.h). */
#ifndef BHCL_GRID_WALKCAP
#define BHCL_GRID_WALKCAP 0
#endif
#define BHCL_GRID_WALKBUF (BHCL_GRID_WALKCAP > 0 ? BHCL_GRID_WALKCAP : 1)

#if BHCL_GRID_VTOPK
#if BHCL_KMAX > 64
#error "the register top-k holds at most 64 entries"
#endif
/* 1 register for k <= 16, else 4 (k <= 64). */
#if BHCL_KMAX <= 16
#define VR 1
#else
#define VR 4
#endif

/* 1: the register list's first k entries are appended unordered and sorted once by a bitonic
 * network (vt_sort), instead of k insertions of VR register steps each: at k = 50 the insertions
 * that fill the list were most of a query's list work (1.4x the queries per second, Cornell 1M).
 * Same (distance, index) order, so the rows are unchanged. Default for four registers only: with
 * one (k <= 16) an insertion is one step and the sort's call and stores cost 3-5 % more. */
#ifndef BHCL_GRID_FILLSORT
#define BHCL_GRID_FILLSORT (VR > 1)
#endif
#ifndef BHCL_GRID_SORT_CALL /* 1: the network in one function (not inlined) over the list in memory */
#define BHCL_GRID_SORT_CALL 1
#endif

typedef struct bhcl_vtopk {
  float16 d0;
  int16 i0;
#if VR > 1
  float16 d1, d2, d3;
  int16 i1, i2, i3;
#endif
  float max_r2;
#if BHCL_GRID_FILLSORT
  /* The first k candidates (d <= max_r2) are only appended here, at lanes 16 VR - k.. of the
   * list's layout, and sorted once when the k-th arrives (vt_sort); the registers keep vt_init's
   * pattern meanwhile, so vt_bound is max_r2 as it is for a list not yet full. n: the entries
   * appended (n == k: sorted, the registers hold the list). */
  uint n, k;
  float* fd; /* 16 VR entries each, the kernel's (so the struct stays in registers) */
  int* fi;
#endif
} bhcl_vtopk;

/* Whether any lane of a comparison's int16 result is set. OpenCL's any() is PoCL's library
 * function, one lane at a time: each vt_insert's test for a tie (vmovd and a test per lane) was a
 * fifth of the kernel's samples on Autzen at k = 10 (Intel Xeon, AVX-512). clang's vector
 * reduction over the compare compiles to one kortestw there. BHCL_GRID_REDUCE 0: any(). */
#ifndef BHCL_GRID_REDUCE
#define BHCL_GRID_REDUCE 1
#endif
#if defined(__has_builtin)
#if BHCL_GRID_REDUCE && __has_builtin(__builtin_reduce_or)
#define BHCL_ANY16(m) (__builtin_reduce_or(m) != 0)
#endif
#endif
#ifndef BHCL_ANY16
#define BHCL_ANY16(m) any(m)
#endif

#define VT_SHIFT ((uint16)(31, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14))
/* The list's registers P d0.. / P i0.. (P: "t->", "t." or nothing) to and from 16 VR floats / ints. */
#if VR > 1
#define VT_STORE(P, FD, FI)                                                          \
  {                                                                                  \
    vstore16(P d0, 0, FD), vstore16(P d1, 1, FD), vstore16(P d2, 2, FD), vstore16(P d3, 3, FD); \
    vstore16(P i0, 0, FI), vstore16(P i1, 1, FI), vstore16(P i2, 2, FI), vstore16(P i3, 3, FI); \
  }
#define VT_LOAD(P, FD, FI)                                                                    \
  {                                                                                           \
    P d0 = vload16(0, FD), P d1 = vload16(1, FD), P d2 = vload16(2, FD), P d3 = vload16(3, FD); \
    P i0 = vload16(0, FI), P i1 = vload16(1, FI), P i2 = vload16(2, FI), P i3 = vload16(3, FI); \
  }
#else
#define VT_STORE(P, FD, FI) \
  {                         \
    vstore16(P d0, 0, FD);  \
    vstore16(P i0, 0, FI);  \
  }
#define VT_LOAD(P, FD, FI) \
  {                        \
    P d0 = vload16(0, FD); \
    P i0 = vload16(0, FI); \
  }
#endif
/* One register: lanes ranking after the candidate take their left neighbour (PD/PI's lane 15 for
 * lane 0) or the candidate, whichever ranks after it; the rest stay. GT(A, AI) is "(A, AI) ranks
 * after the candidate": by distance alone when no lane ties the candidate's distance (the common
 * case), by (distance, index) otherwise. */
#define VT_GT_FAST(A, AI) (A > dv)
#define VT_GT_TIES(A, AI) ((A > dv) | ((A == dv) & (AI > iv)))
#define VT_STEP(D, I, PD, PI, GT)                               \
  {                                                             \
    float16 sd = shuffle2(D, PD, VT_SHIFT);                     \
    int16 si = shuffle2(I, PI, VT_SHIFT);                       \
    int16 m = GT(D, I);                                         \
    int16 ms = GT(sd, si);                                      \
    D = select(D, select(dv, sd, ms), m);                       \
    I = select(I, select(iv, si, ms), m);                       \
  }

inline __attribute__((always_inline)) void vt_init(bhcl_vtopk* t, uint k, float max_r2, float* fd,
                                                   int* fi) {
  const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  const int first = 16 * VR - (int)k;
  t->d0 = select((float16)(INFINITY), (float16)(-INFINITY), lane < (int16)(first));
  t->i0 = (int16)(BHCL_EMPTY_SLOT_ID);
#if VR > 1
  t->d1 = select((float16)(INFINITY), (float16)(-INFINITY), lane + 16 < (int16)(first));
  t->d2 = select((float16)(INFINITY), (float16)(-INFINITY), lane + 32 < (int16)(first));
  t->d3 = select((float16)(INFINITY), (float16)(-INFINITY), lane + 48 < (int16)(first));
  t->i1 = t->i2 = t->i3 = (int16)(BHCL_EMPTY_SLOT_ID);
#endif
  t->max_r2 = max_r2;
#if BHCL_GRID_FILLSORT
  t->n = 0;
  t->k = k;
  t->fd = fd;
  t->fi = fi;
  VT_STORE(t->, fd, fi);
#endif
}

inline __attribute__((always_inline)) float vt_bound(const bhcl_vtopk* t) {
#if VR > 1
  return fmin(t->max_r2, t->d3.sf);
#else
  return fmin(t->max_r2, t->d0.sf);
#endif
}

inline __attribute__((always_inline)) void vt_insert(bhcl_vtopk* t, float d, int id) {
  const float16 dv = (float16)(d);
  const int16 iv = (int16)(id);
#if VR > 1
  const int tie = BHCL_ANY16((t->d0 == dv) | (t->d1 == dv) | (t->d2 == dv) | (t->d3 == dv));
#else
  const int tie = BHCL_ANY16(t->d0 == dv);
#endif
  if (tie) {
#if VR > 1
    VT_STEP(t->d3, t->i3, t->d2, t->i2, VT_GT_TIES);
    VT_STEP(t->d2, t->i2, t->d1, t->i1, VT_GT_TIES);
    VT_STEP(t->d1, t->i1, t->d0, t->i0, VT_GT_TIES);
#endif
    VT_STEP(t->d0, t->i0, dv, iv, VT_GT_TIES);
  } else {
#if VR > 1
    VT_STEP(t->d3, t->i3, t->d2, t->i2, VT_GT_FAST);
    VT_STEP(t->d2, t->i2, t->d1, t->i1, VT_GT_FAST);
    VT_STEP(t->d1, t->i1, t->d0, t->i0, VT_GT_FAST);
#endif
    VT_STEP(t->d0, t->i0, dv, iv, VT_GT_FAST);
  }
}

#if BHCL_GRID_FILLSORT
/* Bitonic sort of the 16 VR lanes ascending by (distance, index). A compare-exchange of lanes g
 * and g ^ J within a register: each lane takes the lesser of itself and its partner where it is
 * the lower lane of an ascending block (or the upper of a descending one), else the greater. */
#define VT_LT(A, AI, B, BI) ((A < B) | ((A == B) & (AI < BI)))
#define VT_CE_IN(D, I, R, SIZE, J)                                                  \
  {                                                                                 \
    const int16 g = lane + (int16)(16 * (R));                                       \
    const int16 tm = ((g & (int16)(J)) == (int16)(0)) == ((g & (int16)(SIZE)) == (int16)(0)); \
    const uint16 pm = as_uint16(lane ^ (int16)(J));                                 \
    float16 pd = shuffle(D, pm);                                                    \
    int16 pi = shuffle(I, pm);                                                      \
    int16 keep = VT_LT(D, I, pd, pi) == tm;                                         \
    D = select(pd, D, keep);                                                        \
    I = select(pi, I, keep);                                                        \
  }
/* Registers A (lower) and B (upper) exchanged lane by lane; ASC: A takes the lesser. */
#define VT_CE_X(A, AI, B, BI, ASC)                \
  {                                               \
    int16 lt = VT_LT(A, AI, B, BI);               \
    if (!(ASC)) lt = ~lt;                         \
    float16 na = select(B, A, lt);                \
    int16 nai = select(BI, AI, lt);               \
    B = select(A, B, lt);                         \
    BI = select(AI, BI, lt);                      \
    A = na;                                       \
    AI = nai;                                     \
  }
/* The intra-register stages J = 8, 4, 2, 1 of a merge of blocks of SIZE, on every register. */
#if VR > 1
#define VT_CE_ALL(P, SIZE, J)             \
  VT_CE_IN(P d0, P i0, 0, SIZE, J);       \
  VT_CE_IN(P d1, P i1, 1, SIZE, J);       \
  VT_CE_IN(P d2, P i2, 2, SIZE, J);       \
  VT_CE_IN(P d3, P i3, 3, SIZE, J)
#else
#define VT_CE_ALL(P, SIZE, J) VT_CE_IN(P d0, P i0, 0, SIZE, J)
#endif
#define VT_MERGE_IN(P, SIZE) \
  VT_CE_ALL(P, SIZE, 8);     \
  VT_CE_ALL(P, SIZE, 4);     \
  VT_CE_ALL(P, SIZE, 2);     \
  VT_CE_ALL(P, SIZE, 1)
/* The whole network on registers P d0.. P d3 (P: "t->" or nothing): blocks of 2, 4, 8, 16 within
 * each register, then (four registers) of 32 and 64 across them. */
#define VT_SORT16(P)        \
  {                         \
    VT_CE_ALL(P, 2, 1);     \
    VT_CE_ALL(P, 4, 2);     \
    VT_CE_ALL(P, 4, 1);     \
    VT_CE_ALL(P, 8, 4);     \
    VT_CE_ALL(P, 8, 2);     \
    VT_CE_ALL(P, 8, 1);     \
    VT_MERGE_IN(P, 16);     \
  }
#if VR > 1
#define VT_SORT_REGS(P)                                   \
  {                                                       \
    VT_SORT16(P);                                         \
    /* blocks of 32: 0-1 ascending, 2-3 descending */     \
    VT_CE_X(P d0, P i0, P d1, P i1, 1);                   \
    VT_CE_X(P d2, P i2, P d3, P i3, 0);                   \
    VT_MERGE_IN(P, 32);                                   \
    /* the whole list, ascending */                       \
    VT_CE_X(P d0, P i0, P d2, P i2, 1);                   \
    VT_CE_X(P d1, P i1, P d3, P i3, 1);                   \
    VT_CE_X(P d0, P i0, P d1, P i1, 1);                   \
    VT_CE_X(P d2, P i2, P d3, P i3, 1);                   \
    VT_MERGE_IN(P, 64);                                   \
  }
#else
#define VT_SORT_REGS(P) VT_SORT16(P)
#endif

#if BHCL_GRID_SORT_CALL
/* The network once, in memory: called from every scan site, instead of a copy at each. */
__attribute__((noinline)) void vt_sort_mem(float* fd, int* fi) {
  const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  float16 d0, d1, d2, d3;
  int16 i0, i1, i2, i3;
  VT_LOAD(, fd, fi);
  VT_SORT_REGS()
  VT_STORE(, fd, fi);
}
#endif

inline __attribute__((always_inline)) void vt_sort(bhcl_vtopk* t) {
#if BHCL_GRID_SORT_CALL
  vt_sort_mem(t->fd, t->fi);
#endif
  VT_LOAD(t->, t->fd, t->fi);
#if !BHCL_GRID_SORT_CALL
  const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  VT_SORT_REGS(t->)
#endif
}

/* A candidate within the bound: appended while the list fills (sorted when the k-th arrives),
 * then inserted. */
#define VT_OFFER(t, d, id)                                 \
  {                                                        \
    if ((t)->n < (t)->k) {                                 \
      const uint at = 16u * VR - (t)->k + (t)->n;          \
      (t)->fd[at] = (d);                                   \
      (t)->fi[at] = (id);                                  \
      if (++(t)->n == (t)->k) vt_sort(t);                  \
    } else {                                               \
      vt_insert((t), (d), (id));                           \
    }                                                      \
  }
/* After the search: a list that did not fill is sorted now. */
#define VT_FINISH(t) \
  if ((t)->n < (t)->k) vt_sort(t)
#else
#define VT_OFFER(t, d, id) vt_insert((t), (d), (id))
#define VT_FINISH(t)
#endif

/* Points [a, b) of the sorted arrays, 16 at a time (the arrays are padded by 16 entries). walk (a
 * constant at each call): a run of the far walk (its rows of a level-2 node, its fine cells), where
 * a run of BHCL_GRID_SHORT_RUN points or fewer is measured one point at a time instead of the 16
 * lanes' loads and the reduction of their mask (two clusters at k = 10 average 1.3 points a run
 * there). The same sums (FP_CONTRACT OFF), so the same distances. The rings' runs (cells of the
 * target population, on the data) keep the lanes alone. (One offer loop for both ways, the short
 * run's distances stored as the lanes' are, compiled 5-10 % faster and ran 5 % slower: 0.92 / 1.16
 * of FLANN on two clusters at k = 10 / 50 against 0.97 / 1.28, one process.) */
inline __attribute__((always_inline)) void vt_scan(bhcl_vtopk* t, float3 q, __global const float* px,
                                                   __global const float* py, __global const float* pz,
                                                   __global const int* pid, uint a, uint b, int walk) {
  const int16 lanebit = (int16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192,
                                16384, 32768);
  const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
#if BHCL_GRID_PREFETCH > 0 && BHCL_GRID_PREFETCH_IDS
  __builtin_prefetch(pid + a);
#endif
  if (walk && b - a <= BHCL_GRID_SHORT_RUN) {
    for (uint p = a; p < b; ++p) {
      const float d = bhcl_dist2_xyz(q.x, q.y, q.z, px[p], py[p], pz[p]);
      if (d <= vt_bound(t)) VT_OFFER(t, d, pid[p]);
    }
    return;
  }
  for (uint p = a; p < b; p += 16) {
    float16 dx = (float16)(q.x) - vload16(0, px + p);
    float16 dy = (float16)(q.y) - vload16(0, py + p);
    float16 dz = (float16)(q.z) - vload16(0, pz + p);
    float16 d = dx * dx + dy * dy + dz * dz;
    float bound = vt_bound(t);
    const int16 in = (d <= (float16)(bound)) & (lane < (int16)((int)(b - p)));
#if BHCL_GRID_REDUCE
    /* Most chunks offer nothing: that test alone first (a kortestw), the lanes' bits after. */
    if (!BHCL_ANY16(in)) continue;
#endif
    int16 w = in & lanebit;
    int8 w8 = w.lo | w.hi;
    int4 w4 = w8.lo | w8.hi;
    int2 w2 = w4.lo | w4.hi;
    uint mask = (uint)(w2.x | w2.y);
    if (mask == 0u) continue;
    float dd[16];
    vstore16(d, 0, dd);
    while (mask) {
      int j = 31 - (int)clz(mask & (0u - mask));
      mask &= mask - 1u;
      /* Offered without testing the bound again: a lane past it now (the list took a nearer
       * point of this chunk) leaves an insertion unchanged, and the list's fill takes only lanes
       * under max_r2. The test's branch, taken at random, cost more than the insertions it saved:
       * +2-34 % (median 11 %) over the 12 exact rows, k = 10 and 50 (Intel Xeon, AVX-512). */
      VT_OFFER(t, dd[j], pid[p + (uint)j]);
    }
  }
}

#define BHCL_GRID_STATE bhcl_vtopk
#define BHCL_GRID_BOUND(st) vt_bound(st)
#define BHCL_GRID_SCAN(st, a, b) vt_scan(st, (float3)(qx, qy, qz), px, py, pz, pid, a, b, 0)
#define BHCL_GRID_SCAN_WALK(st, a, b) vt_scan(st, (float3)(qx, qy, qz), px, py, pz, pid, a, b, 1)

#else /* the scalar list */

typedef struct bhcl_stopk {
  float d[BHCL_KMAX];
  int i[BHCL_KMAX];
  uint k, n;
  float max_r2;
} bhcl_stopk;

inline float st_bound(const bhcl_stopk* t) { return fmin(t->max_r2, t->d[t->k - 1]); }

inline void st_scan(bhcl_stopk* t, float qx, float qy, float qz, __global const float* px,
                    __global const float* py, __global const float* pz, __global const int* pid,
                    uint a, uint b) {
  for (uint p = a; p < b; ++p) {
    float d = bhcl_dist2_xyz(qx, qy, qz, px[p], py[p], pz[p]);
    if (d <= st_bound(t) && bhcl_topk_accepts(t->d, t->i, t->k, d, pid[p]))
      t->n = bhcl_topk_push(t->d, t->i, t->k, t->n, d, pid[p]);
  }
}

#define BHCL_GRID_STATE bhcl_stopk
#define BHCL_GRID_BOUND(st) st_bound(st)
#define BHCL_GRID_SCAN(st, a, b) st_scan(st, qx, qy, qz, px, py, pz, pid, a, b)
#endif

#include "grid_search.h"

/* The cell of q offset by (dx, dy, dz), x clamped into the grid; 0xffffffff when its row lies
 * outside the grid. */
inline uint bhcl_grid_near_cell(const bhcl_grid_geom g, float3 q, int dx, int dy, int dz) {
  int x = (int)bhcl_grid_cell(q.x, g.ox, g.inv_h, g.nx) + dx;
  int y = (int)bhcl_grid_cell(q.y, g.oy, g.inv_h, g.ny) + dy;
  int z = (int)bhcl_grid_cell(q.z, g.oz, g.inv_h, g.nz) + dz;
  if (y < 0 || y >= (int)g.ny || z < 0 || z >= (int)g.nz) return 0xffffffffu;
  x = x < 0 ? 0 : (x >= (int)g.nx ? (int)g.nx - 1 : x);
  return ((uint)z * g.ny + (uint)y) * g.nx + (uint)x;
}

__kernel void blockhash_grid_knn(__global const uint* starts, __global const float* px,
                                 __global const float* py, __global const float* pz,
                                 __global const int* pid, __global const uchar* occ, float4 geo0, float4 geo1, uint4 dims,
                                 float4 box_lo, float4 box_hi,
                                 BHCL_KNN_QUERY_PARAMS, uint budget, BHCL_KNN_RESULT_PARAMS,
                                 __global int* out_examined, uint want_examined) {
  uint gid = get_global_id(0);
  if (gid >= count) return;
  ulong row = first + gid;
  float3 q = bhcl_load_query(queries, row);
  const float qx = q.x, qy = q.y, qz = q.z;
  const bhcl_grid_geom g = bhcl_grid_geom_from(geo0, geo1, dims);
  const bhcl_grid_dbox db = bhcl_grid_dbox_from(box_lo, box_hi);
#if BHCL_GRID_PREFETCH > 0
  /* Two stages, so that neither load waits: the directory entries of the query 2d work-items
   * ahead, the points of the query d ahead (its entries fetched d items ago). Either the home
   * cell only or (RING) the first cell of each of the 9 rows around it, which the first rings
   * scan: in a random query order each is a cache miss. */
#if BHCL_GRID_PREFETCH_RING
#define BHCL_GRID_PF_ROWS 9
#else
#define BHCL_GRID_PF_ROWS 1
#endif
  if (BHCL_GRID_PREFETCH_DIR && gid + 2 * BHCL_GRID_PREFETCH < count) {
    float3 fq = bhcl_load_query(queries, row + 2 * BHCL_GRID_PREFETCH);
    if (bhcl_query_is_finite(fq))
      for (int j = 0; j < BHCL_GRID_PF_ROWS; ++j) {
        /* the home cell, or the first cell (x - 1) of row j of the 3 x 3 around it */
        uint c = BHCL_GRID_PF_ROWS == 1 ? bhcl_grid_near_cell(g, fq, 0, 0, 0)
                                        : bhcl_grid_near_cell(g, fq, -1, j % 3 - 1, j / 3 - 1);
        if (c != 0xffffffffu) __builtin_prefetch(starts + (g.sparse ? (c >> BHCL_GRID_SEG_BITS) : c));
      }
  }
  if (gid + BHCL_GRID_PREFETCH < count) {
    float3 nq = bhcl_load_query(queries, row + BHCL_GRID_PREFETCH);
    if (bhcl_query_is_finite(nq))
      for (int j = 0; j < BHCL_GRID_PF_ROWS; ++j) {
        /* the home cell, or the first cell (x - 1) of row j of the 3 x 3 around it */
        uint c = BHCL_GRID_PF_ROWS == 1 ? bhcl_grid_near_cell(g, nq, 0, 0, 0)
                                        : bhcl_grid_near_cell(g, nq, -1, j % 3 - 1, j / 3 - 1);
        if (c == 0xffffffffu) continue;
        uint s = bhcl_grid_start(starts, g.sparse, c);
        for (int l = 0; l < BHCL_GRID_PREFETCH_LINES; ++l, s += 16) {
          __builtin_prefetch(px + s);
          __builtin_prefetch(py + s);
          __builtin_prefetch(pz + s);
          if (BHCL_GRID_PREFETCH_IDS) __builtin_prefetch(pid + s);
        }
      }
  }
#undef BHCL_GRID_PF_ROWS
#endif
  uint examined = 0;
  const ulong orow = bhcl_out_row(out_rows, remap, row);
#if BHCL_GRID_VTOPK
  bhcl_vtopk t;
  float fill_d[16 * VR];
  int fill_i[16 * VR];
  vt_init(&t, k, max_r2, fill_d, fill_i);
  if (bhcl_query_is_finite(q)) examined = bhcl_grid_search(starts, px, py, pz, pid, occ, g, db, qx, qy, qz, budget, BHCL_GRID_ROWCAP, BHCL_GRID_FINE_RINGS, BHCL_GRID_WALKCAP, k, &t);
  VT_FINISH(&t);
  float td[16 * VR];
  int ti[16 * VR];
  VT_STORE(t., td, ti);
  const uint off = 16u * VR - k;
  bhcl_write_row(out_ids, out_d2, out_counts, orow, k, td + off, ti + off);
#else
  bhcl_stopk t;
  t.k = k;
  t.n = 0;
  t.max_r2 = max_r2;
  bhcl_topk_init(t.d, t.i, k);
  if (bhcl_query_is_finite(q)) examined = bhcl_grid_search(starts, px, py, pz, pid, occ, g, db, qx, qy, qz, budget, BHCL_GRID_ROWCAP, BHCL_GRID_FINE_RINGS, BHCL_GRID_WALKCAP, k, &t);
  bhcl_write_row(out_ids, out_d2, out_counts, orow, k, t.d, t.i);
#endif
  if (want_examined) out_examined[orow] = (int)examined;
}
