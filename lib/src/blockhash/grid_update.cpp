// GridIndex: points added and removed without a fresh build (issue 23; Index::insert/remove).
//
// The grid layout natively, through the Grid's public arrays and build_grid only (the grid's
// build, its file format and its kernels are unchanged):
//  - remove: the point becomes a hole in place: x = y = z = +inf, id = BHCL_EMPTY_SLOT_ID. The
//    kernels need no change: a hole's distance is +inf, never within a finite bound, and
//    (+inf, 0x7fffffff) never ranks before an empty slot of the top-k list (the same pair), so it
//    is never returned. Holes still count as examined points of a budget, so past 1/8 of the stored
//    points they are compacted (one stable pass, in place).
//  - insert, points inside the grid's box: the B+ tree's leaf insert done in bulk. A counting
//    sort of the new points alone into the existing cells, then one parallel pass over ranges of
//    cells moving each cell's run to its new start (moved right by the new points before it) with
//    its new points behind it: in place where the arrays have room (the build reserves an eighth),
//    else into scratch arrays that then change places with the grid's (O(N) moves, no tuning, no
//    sort of the old points). The two-level directory merges the same way (merge_two_level_points,
//    its starts moved in place). Ids stay ascending inside a cell (new ids are larger), as a fresh
//    build's stable scatter gives them.
//  - the leaf split: a cell side tuned for a population (target_cell_points) stops fitting when
//    the set grows or shrinks; once the point-weighted mean cell population drifts past 1.1x (or
//    below 0.9x) of the last full build's, the grid is rebuilt over the live points with a freshly
//    tuned side. Growth by doubling keeps the amortised cost per point O(1).
//  - points outside the grid's box: a full build over the live points (the slab bounds, and so
//    the exact mode, rely on every point lying inside its cell). Every full build an update makes
//    (this one, the band's) is one fresh build with the build's own
//    parameters, never two: no update costs more than building its result afresh (issue 39).
//  - device buffers: the changed tail of each array written in place where it fits, reallocated
//    with capacity grown by half where not (upload_grid); on a host-in-place device (PoCL's CPU
//    device, Quirks::host_ptr_in_place) views of the host arrays, made again after the update.
// The L tables are rebuilt over the live points on every update (BlockTablesIndex::blocks_update,
// tables_index.cpp): their Hilbert blocks and tables have no cheap insert.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <cstdio>
#include <cstdlib>

#include "bhcl_shared.h"
#include "blockhash/build.hpp"
#include "blockhash/grid_io.hpp"
#include "blockhash/update_counters.hpp"
#include "blockhash_cl/grid_index.hpp"
#include "blockhash_cl/error.hpp"
#include "core/device_util.hpp"
#include "core/parallel.hpp"
#include "core/point_scan.hpp"

namespace bhcl {
namespace {

constexpr std::int32_t kHoleId = BHCL_EMPTY_SLOT_ID;
// The band of mean cell populations (relative to the tuned side's) an update keeps the cells in:
// outside it the side is retuned by a full build. Recall at a given A follows the population
// (uniform 1M, k = 10, fresh builds tuned for 19 .. 30 points per cell: at A = 8 recall 0.941 ..
// 0.897, at A = 16 0.995 .. 0.980; at A = 2, where the budget is about one cell, 0.71 .. 0.59),
// so the band is narrow: +-10 % keeps A >= 4 within about 0.01 of a fresh build. It is just wide
// enough that inserting or removing a tenth of the points from the same distribution (the
// point-weighted mean moves by (0.1 lambda) / (lambda + 1), 9.6 % at 24) merges instead of
// rebuilding; growth by 1.1x per retune still amortises the rebuilds to O(1) per point.
constexpr double kRetuneAbove = 1.10, kRetuneBelow = 0.90;

std::uint32_t cell_of(const bhcl_grid_geom& g, const float* p) { return blockhash::grid_cell_index(g, p[0], p[1], p[2]); }

// Inside the grid's box: [o, o + n h] per axis (in double: the last cell's slab ends there; the
// geometry's margin covers the float rounding of the cell assignment, as for a fresh build's points).
bool inside(const bhcl_grid_geom& g, const float* p) {
  const double o[3] = {g.ox, g.oy, g.oz};
  const double n[3] = {double(g.nx), double(g.ny), double(g.nz)};
  for (int d = 0; d < 3; ++d)
    if (!(double(p[d]) >= o[d] && double(p[d]) <= o[d] + n[d] * double(g.h))) return false;
  return true;
}

// The new points of an insert sorted by cell (a counting sort, stable): record j is
// (x, y, z, index i as bits) at rec[4 j ..], cell c's at j in [add[c], add[c + 1]). Read in
// order by the merge and the node boxes (each read the points through an index per point
// before: two random gathers, a fifth of a 10 % insert at 1M). The records live in the build's
// scratch (GridScratch::rec, 16 bytes per point of the build, already faulted in).
inline void put_new_point(float* X, float* Y, float* Z, std::int32_t* I, std::size_t p, const float* r, std::int32_t first) {
  std::uint32_t i;
  std::memcpy(&i, r + 3, 4);
  X[p] = r[0];
  Y[p] = r[1];
  Z[p] = r[2];
  I[p] = first + static_cast<std::int32_t>(i);
}

// The merge of an insert, out of place, in parallel over ranges of cells: each cell's run copied
// to its new start (the old start plus the new points of the cells before it, add[c]) with its
// new points (records add[c] .. of rec, ids first + i) behind it, into the scratch arrays (sized n1 + pad).
// Cells before first_cell keep their places.
void merge_into_scratch(const blockhash::Grid& g, const float* rec, std::size_t m, std::int32_t first,
                        const std::uint32_t* add, std::size_t first_cell, blockhash::GridScratch& sc) {
  const std::size_t nc = g.ncells(), n1 = g.n_points + m;
  const unsigned T = static_cast<unsigned>(std::min<std::size_t>(detail::default_threads(), std::max<std::size_t>(1, n1 / 65536)));
  // Cell ranges of about equal output: thread t starts at the first cell whose new start passes
  // t n1 / T.
  std::vector<std::size_t> cut(T + 1, nc);
  cut[0] = 0;
  for (unsigned t = 1, c = 0; t < T; ++t) {
    const std::size_t want = std::size_t(t) * n1 / T;
    while (c < nc && std::size_t(g.starts[c]) + add[c] < want) ++c;
    cut[t] = c;
  }
  {
    const std::uint32_t* const st = g.starts.data();
    const std::uint32_t* const ad = add;
    const float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
    const std::int32_t* const I = g.ids.data();
    float *const X2 = sc.x.data(), *const Y2 = sc.y.data(), *const Z2 = sc.z.data();
    std::int32_t* const I2 = sc.ids.data();
    detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
          for (std::size_t t = tb; t < te; ++t) {
            const std::size_t c0 = cut[t], c1 = cut[t + 1];
            if (c0 >= c1) continue;
            // The cells before the first receiving one keep their places.
            const std::size_t s0 = st[c0], s1 = st[c1];
            const std::size_t keep = c1 <= first_cell ? s1 : c0 < first_cell ? st[first_cell] : s0;
            std::memcpy(X2 + s0, X + s0, (keep - s0) * 4);
            std::memcpy(Y2 + s0, Y + s0, (keep - s0) * 4);
            std::memcpy(Z2 + s0, Z + s0, (keep - s0) * 4);
            std::memcpy(I2 + s0, I + s0, (keep - s0) * 4);
            for (std::size_t c = std::max(c0, first_cell); c < c1; ++c) {
              const std::size_t a = st[c], len = st[c + 1] - a, dst = a + ad[c], k = ad[c + 1] - ad[c];
              std::memcpy(X2 + dst, X + a, len * 4);
              std::memcpy(Y2 + dst, Y + a, len * 4);
              std::memcpy(Z2 + dst, Z + a, len * 4);
              std::memcpy(I2 + dst, I + a, len * 4);
              for (std::size_t j = 0; j < k; ++j) put_new_point(X2, Y2, Z2, I2, dst + len + j, rec + 4 * (ad[c] + j), first);
            }
          }
        });
  }
}

// The two-level directory's merge (issue 39: every insert there was a full build, 100 inserts
// growing a clustered set 10x took 8 s). The new points sorted by cell (key: cell << 32 | index,
// so stable), then one pass over the segments writing the new directory (a segment receiving its
// first points gets its table; every start moves right by the new points before it) and a merge
// of the points out of place, in parallel over ranges of the sorted new points. The old point at
// slot p of cell c goes to p + (new points in cells < c); the j-th new point (sorted) of cell c to
// start(c + 1) + j: behind the cell's old points, ids ascending as a fresh build's stable scatter
// puts them. Holes move with their cells (a remove compacts past 1/8 of them, as before).
struct TwoLevelAdd {
  std::vector<std::uint64_t> key;        // cell << 32 | index, ascending
  double sum2 = 0;                       // the squared cell populations' sum after the insert
  std::size_t occupied = 0;              // occupied cells after it
  std::vector<std::uint32_t> new_cells;  // cells that were empty and receive points, ascending
  std::vector<std::uint32_t> new_segs;   // segments that receive their first points, ascending
};

TwoLevelAdd two_level_additions(const blockhash::Grid& g, const float* scaled, std::size_t m, double sum2_before,
                                std::size_t occupied_before) {
  TwoLevelAdd a;
  a.key.resize(m);
  for (std::size_t i = 0; i < m; ++i) a.key[i] = (std::uint64_t(cell_of(g.geom, scaled + 3 * i)) << 32) | i;
  std::sort(a.key.begin(), a.key.end());
  a.sum2 = sum2_before;
  a.occupied = occupied_before;
  for (std::size_t j = 0; j < m;) {
    const std::uint32_t c = static_cast<std::uint32_t>(a.key[j] >> 32);
    std::size_t e = j;
    while (e < m && (a.key[e] >> 32) == c) ++e;
    const double old = double(g.start(c + 1) - g.start(c)), v = old + double(e - j);
    a.sum2 += v * v - old * old;
    if (old == 0) {
      ++a.occupied;
      a.new_cells.push_back(c);
    }
    const std::uint32_t seg = c >> BHCL_GRID_SEG_BITS;
    if ((g.starts[seg] & BHCL_GRID_EMPTY_SEG) && (a.new_segs.empty() || a.new_segs.back() != seg)) a.new_segs.push_back(seg);
    j = e;
  }
  return a;
}

// The directory updated in place: every start from the first receiving segment on moves right by
// the new points before it (an empty segment's run value, an occupied one's 16 entries), and a
// segment receiving its first points gets a table appended past the others (the kernels follow
// the top entry, in any order). Parallel over ranges of segments, each starting from the new
// points before it (a binary search in the sorted keys). The whole directory was written anew
// before: 30 MB for a clustered 1M set whose cells number 117M, more than the merge of the points.
void two_level_directory_in_place(blockhash::Grid& g, const TwoLevelAdd& a, unsigned threads) {
  constexpr std::uint32_t kSeg = 1u << BHCL_GRID_SEG_BITS;
  const std::size_t top = blockhash::Grid::top_entries(g.ncells()), m = a.key.size();
  const std::size_t old_size = g.starts.size(), new_size = old_size + a.new_segs.size() * kSeg;
  if (new_size > g.starts.capacity()) g.starts.reserve(new_size + new_size / 8);  // room for the next inserts' tables
  g.starts.resize(new_size);
  std::uint32_t* const st = g.starts.data();
  const std::size_t s_first = std::size_t(a.key.front() >> (32 + BHCL_GRID_SEG_BITS));
  detail::parallel_chunks(top - s_first, std::size_t(1) << 16, threads, [&](std::size_t, std::size_t sb, std::size_t se) {
    sb += s_first, se += s_first;
    const std::uint64_t from = std::uint64_t(sb) << (32 + BHCL_GRID_SEG_BITS);
    std::size_t j = std::size_t(std::lower_bound(a.key.begin(), a.key.end(), from) - a.key.begin());
    std::size_t r = std::size_t(std::lower_bound(a.new_segs.begin(), a.new_segs.end(), std::uint32_t(sb)) - a.new_segs.begin());
    std::uint32_t added = static_cast<std::uint32_t>(j);
    for (std::size_t sg = sb; sg < se; ++sg) {
      const std::uint32_t e = st[sg];
      const bool gets = j < m && (a.key[j] >> (32 + BHCL_GRID_SEG_BITS)) == sg;
      if (!gets) {  // no new point here: every start moves by the same count
        if (e & BHCL_GRID_EMPTY_SEG) st[sg] = BHCL_GRID_EMPTY_SEG | ((e & ~BHCL_GRID_EMPTY_SEG) + added);
        else if (added)
          for (std::uint32_t c = 0; c < kSeg; ++c) st[e + c] += added;
        continue;
      }
      std::uint32_t* table;
      if (e & BHCL_GRID_EMPTY_SEG) {  // its first points: a table of the run's start
        const std::uint32_t slot = static_cast<std::uint32_t>(old_size + r++ * kSeg);
        table = st + slot;
        std::fill(table, table + kSeg, e & ~BHCL_GRID_EMPTY_SEG);
        st[sg] = slot;
      } else {
        table = st + e;
      }
      for (std::uint32_t c = 0; c < kSeg; ++c) {
        const std::uint64_t cell = (std::uint64_t(sg) << BHCL_GRID_SEG_BITS) | c;
        table[c] += added;
        while (j < m && (a.key[j] >> 32) == cell) ++added, ++j;
      }
    }
  });
}

// The point boxes of the pyramid's nodes of level >= 2 (stored after its bits) widened by the
// new points. visit(cb, ce, emit) calls emit(cell, x, y, z) for each new point of cells [cb, ce)
// in cell order, so a level-2 node's new points of a row come together: their box is taken
// first, then written into the level-2 node unless it holds it already. In parallel over ranges
// of level-2 z slabs (each owns its level-2 boxes); the boxes that widened a level-2 node then
// go up, serially, until a node already holds them (its ancestors' boxes hold its own). A walk
// per point through every level, with the cell's coordinates by divisions and the point read
// through an index, was a sixth of a 10 % insert at 1M.
template <class Visit>
void node_boxes_add_points(blockhash::Grid& g, std::size_t m, unsigned threads, Visit&& visit) {
  const bhcl_grid_geom& gm = g.geom;
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(gm, &top_off, &total);
  if (top < 2 || m == 0) return;
  std::uint8_t* const boxes = g.occ.data() + bhcl_grid_tbox_off(total);
  std::vector<std::size_t> at(top + 1, 0);  // the first box of level l
  for (std::uint32_t l = 3; l <= top; ++l) at[l] = at[l - 1] + bhcl_grid_occ_size(gm, l - 1);
  const std::size_t nx = gm.nx, nxy = std::size_t(gm.nx) * gm.ny, nz = gm.nz;
  const bhcl_grid_dbox empty{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
  struct Up {
    std::uint32_t x, y, z;  // a cell of the node
    bhcl_grid_dbox box;
  };
  // Widens node (x, y, z) of level l by nb; false when it held nb already.
  auto widen = [&](std::uint32_t l, std::uint32_t x, std::uint32_t y, std::uint32_t z, const bhcl_grid_dbox& nb) {
    const std::size_t at_node = bhcl_grid_occ_index(gm, std::uint32_t(at[l]), l, x >> l, y >> l, z >> l);
    bhcl_grid_dbox b;  // memcpy: the boxes sit at 4-byte offsets of a byte buffer
    std::memcpy(&b, boxes + at_node * sizeof(b), sizeof(b));
    if (b.lx <= nb.lx && nb.hx <= b.hx && b.ly <= nb.ly && nb.hy <= b.hy && b.lz <= nb.lz && nb.hz <= b.hz) return false;
    blockhash::unite_box(b, nb);
    std::memcpy(boxes + at_node * sizeof(b), &b, sizeof(b));
    return true;
  };
  const std::size_t slabs = bhcl_grid_occ_dim(gm.nz, 2);
  // Ranges of slabs handed out in turn, up to 4 per thread (a thread that starts late takes fewer).
  const unsigned T = m >= 65536 ? std::max(1u, std::min<unsigned>(threads ? threads : detail::default_threads(), unsigned(slabs))) : 1u;
  const std::size_t R = T > 1 ? std::min<std::size_t>(slabs, 4 * std::size_t(T)) : 1;
  std::vector<std::vector<Up>> up(R);
  detail::parallel_chunks(
      R, 1, T,
      [&](std::size_t, std::size_t tb, std::size_t te) {
        for (std::size_t t = tb; t < te; ++t) {
          const std::size_t zb = slabs * t / R, ze = slabs * (t + 1) / R;
          bool have = false;
          std::uint32_t cur = 0, x = 0, y = 0, z = 0;
          std::size_t row0 = 0, row_y = 0, row_z = 0;  // the row of cells holding cur: its first cell, y, z
          bhcl_grid_dbox run = empty;  // the new points of the run's level-2 node, (x, y, z) >> 2
          auto flush = [&] {
            if (widen(2, x, y, z, run)) up[t].push_back(Up{x, y, z, run});
          };
          visit(4 * zb * nxy, std::min(4 * ze, nz) * nxy, [&](std::uint32_t c, float px, float py, float pz) {
            if (!have || c != cur) {
              if (!have || c < row0 || c >= row0 + nx) {  // another row: the divisions once per row
                row_z = c / nxy;
                row_y = (c - row_z * nxy) / nx;
                row0 = row_z * nxy + row_y * nx;
              }
              const std::uint32_t cx = std::uint32_t(c - row0), cy = std::uint32_t(row_y), cz = std::uint32_t(row_z);
              if (!have || (cx >> 2) != (x >> 2) || (cy >> 2) != (y >> 2) || (cz >> 2) != (z >> 2)) {
                if (have) flush();
                x = cx, y = cy, z = cz, run = empty;
              }
              have = true;
              cur = c;
            }
            blockhash::widen_box(run, px, py, pz);
          });
          if (have) flush();
        }
      });
  for (const std::vector<Up>& part : up)
    for (const Up& u : part)
      for (std::uint32_t l = 3; l <= top; ++l)
        if (!widen(l, u.x, u.y, u.z, u.box)) break;
}

// Inserts only add points, so the occupancy pyramid (grid_search.h) only gains bits: each cell
// that held no point and holds some now sets its bit at every level up to the first byte that
// already had one (its parent's bit is set then). O(new cells x levels); build_grid_occupancy
// reads every cell (most of a merge's time for a two-level directory of 117M cells). Then the
// node boxes, from the new points in cell order (node_boxes_add_points).
template <class Visit>
void occupancy_add_cells(blockhash::Grid& g, const std::vector<std::uint32_t>& cells, std::size_t m, unsigned threads,
                         Visit&& visit) {
  const bhcl_grid_geom& gm = g.geom;
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(gm, &top_off, &total);
  if (g.occ.size() != bhcl_grid_occ_bytes(gm)) {  // not built for this geometry: all of it
    blockhash::build_grid_occupancy(g, threads);
    return;
  }
  std::vector<std::uint32_t> off(top + 1, 0);
  for (std::uint32_t l = 2; l <= top; ++l) off[l] = off[l - 1] + bhcl_grid_occ_size(gm, l - 1);
  const std::size_t nx = gm.nx, nxy = std::size_t(gm.nx) * gm.ny;
  for (const std::uint32_t c : cells) {
    const std::uint32_t x = std::uint32_t(c % nx), y = std::uint32_t((c % nxy) / nx), z = std::uint32_t(c / nxy);
    for (std::uint32_t l = 1; l <= top; ++l) {
      const std::uint32_t bit = ((x >> (l - 1)) & 1u) | (((y >> (l - 1)) & 1u) << 1) | (((z >> (l - 1)) & 1u) << 2);
      std::uint8_t& b = g.occ[bhcl_grid_occ_index(gm, off[l], l, x >> l, y >> l, z >> l)];
      const bool had = b != 0;
      b = std::uint8_t(b | (1u << bit));
      if (had) break;
    }
  }
  node_boxes_add_points(g, m, threads, visit);
}

// The points merged into the scratch arrays (n + m + pad), in parallel over ranges of the sorted
// new points cut at cell boundaries: a range copies the old slots of its cells, each cell's new
// points behind its old ones.
void merge_two_level_points(const blockhash::Grid& g, const float* scaled, std::int32_t first, const TwoLevelAdd& a,
                            blockhash::GridScratch& sc) {
  const std::size_t m = a.key.size(), n1 = g.n_points + m;
  const unsigned T = static_cast<unsigned>(std::min<std::size_t>(detail::default_threads(), std::max<std::size_t>(1, n1 / 65536)));
  // Range t: new points [kb[t], kb[t + 1]), cells [cb[t], cb[t + 1]).
  std::vector<std::size_t> kb(T + 1, m), cb(T + 1, g.ncells());
  kb[0] = 0, cb[0] = 0;
  for (unsigned t = 1; t < T; ++t) {
    std::size_t k = std::max(kb[t - 1], std::size_t(t) * m / T);
    while (k > kb[t - 1] && k < m && (a.key[k] >> 32) == (a.key[k - 1] >> 32)) ++k;  // a cell's first
    kb[t] = k;
    cb[t] = k < m ? std::size_t(a.key[k] >> 32) : g.ncells();
  }
  const float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
  const std::int32_t* const I = g.ids.data();
  float *const X2 = sc.x.data(), *const Y2 = sc.y.data(), *const Z2 = sc.z.data();
  std::int32_t* const I2 = sc.ids.data();
  auto copy_old = [&](std::size_t from, std::size_t to, std::size_t shift) {
    std::memcpy(X2 + from + shift, X + from, (to - from) * 4);
    std::memcpy(Y2 + from + shift, Y + from, (to - from) * 4);
    std::memcpy(Z2 + from + shift, Z + from, (to - from) * 4);
    std::memcpy(I2 + from + shift, I + from, (to - from) * 4);
  };
  detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
        for (std::size_t t = tb; t < te; ++t) {
          std::size_t at = g.start(cb[t]);  // the next old slot to copy
          const std::size_t end = g.start(cb[t + 1]);
          for (std::size_t j = kb[t]; j < kb[t + 1];) {
            const std::uint32_t c = static_cast<std::uint32_t>(a.key[j] >> 32);
            const std::size_t cell_end = g.start(c + 1);
            copy_old(at, cell_end, j);  // shifted by the new points before this cell
            at = cell_end;
            for (; j < kb[t + 1] && (a.key[j] >> 32) == c; ++j) {
              const std::size_t i = std::size_t(a.key[j] & 0xffffffffu), p = cell_end + j;
              X2[p] = scaled[3 * i];
              Y2[p] = scaled[3 * i + 1];
              Z2[p] = scaled[3 * i + 2];
              I2[p] = first + static_cast<std::int32_t>(i);
            }
          }
          copy_old(at, end, kb[t + 1]);
        }
      });
}

// v's capacity at least n, with an eighth more when it must grow: a merge's arrays keep room for
// the next insert's merge in place (room not written is never faulted in).
template <typename T>
void reserve_with_room(blockhash::GridVec<T>& v, std::size_t n) {
  if (v.capacity() < n) {
    blockhash::GridVec<T>().swap(v);  // the old contents are not kept (the caller writes all of it)
    v.reserve(n + n / 8);
  }
}

// The merge in place, into the arrays' room past their points: each cell's run moved right by the
// new points of the cells before it (add[c]), from the last cell down, its new points behind it.
// In parallel over ranges of cells: range t writes up to add[c0] slots into the head of range
// t + 1's slots, so those heads are saved first and read from the copy. No fresh memory is
// faulted in but the room the new points take (the out-of-place merge's four new arrays, 17.6 MB
// for a 10 % insert into 1M points, were most of its time: the kernel zeroes every new page).
// Returns false (nothing changed) where the arrays have no room or a range is shorter than the
// head it must save.
bool merge_in_place(blockhash::Grid& g, const float* rec, std::size_t m, std::int32_t first,
                    const std::uint32_t* add, std::size_t first_cell) {
  const std::size_t nc = g.ncells(), n1 = g.n_points + m, want = n1 + blockhash::kGridPad;
  if (g.x.capacity() < want || g.y.capacity() < want || g.z.capacity() < want || g.ids.capacity() < want) return false;
  const std::uint32_t* const st = g.starts.data();
  const unsigned T = static_cast<unsigned>(std::min<std::size_t>(detail::default_threads(), std::max<std::size_t>(1, n1 / 65536)));
  std::vector<std::size_t> cut(T + 1, nc);
  cut[0] = first_cell;
  for (unsigned t = 1, c = unsigned(first_cell); t < T; ++t) {
    const std::size_t from = std::size_t(st[first_cell]) + add[first_cell];
    const std::size_t want_out = from + std::size_t(t) * (n1 - from) / T;
    while (c < nc && std::size_t(st[c]) + add[c] < want_out) ++c;
    cut[t] = std::max<std::size_t>(c, cut[t - 1]);
  }
  // The heads range t - 1 writes over: [st[c0], st[c0] + add[c0]) of each range t >= 1.
  struct Head {
    std::size_t lo = 0, n = 0;
    std::vector<float> x, y, z;
    std::vector<std::int32_t> ids;
  };
  std::vector<Head> head(T);
  for (unsigned t = 1; t < T; ++t) {
    const std::size_t c0 = cut[t], lo = st[c0], n = add[c0];
    if (n > std::size_t(st[cut[t + 1]]) - lo) return false;  // a range shorter than its head
    Head& h = head[t];
    h.lo = lo, h.n = n;
    h.x.assign(g.x.begin() + lo, g.x.begin() + lo + n);
    h.y.assign(g.y.begin() + lo, g.y.begin() + lo + n);
    h.z.assign(g.z.begin() + lo, g.z.begin() + lo + n);
    h.ids.assign(g.ids.begin() + lo, g.ids.begin() + lo + n);
  }
  g.x.resize(want);  // within capacity: the pointers stay
  g.y.resize(want);
  g.z.resize(want);
  g.ids.resize(want);
  float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
  std::int32_t* const I = g.ids.data();
  const std::uint32_t* const ad = add;
  detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
        for (std::size_t t = tb; t < te; ++t) {
          const Head& h = head[t];
          const std::size_t saved_end = h.lo + h.n;
          for (std::size_t c = cut[t + 1]; c-- > cut[t];) {
            const std::size_t a = st[c], len = st[c + 1] - a, dst = a + ad[c], k = ad[c + 1] - ad[c];
            for (std::size_t j = 0; j < k; ++j)  // the new points, behind the cell's old ones
              put_new_point(X, Y, Z, I, dst + len + j, rec + 4 * (ad[c] + j), first);
            if (ad[c] == 0 || len == 0) continue;  // the run stays where it is
            // The run's slots past the saved head move within the arrays (right, overlapping:
            // memmove, the C library's AVX-512 one; an inline chunked copy, built for the
            // baseline x86-64, made a 1 % insert 1.25x slower); those in it come from the copy.
            const std::size_t from = std::max(a, std::min(saved_end, a + len));
            std::memmove(X + dst + (from - a), X + from, (a + len - from) * 4);
            std::memmove(Y + dst + (from - a), Y + from, (a + len - from) * 4);
            std::memmove(Z + dst + (from - a), Z + from, (a + len - from) * 4);
            std::memmove(I + dst + (from - a), I + from, (a + len - from) * 4);
            if (from > a) {
              const std::size_t o = a - h.lo;
              std::memcpy(X + dst, h.x.data() + o, (from - a) * 4);
              std::memcpy(Y + dst, h.y.data() + o, (from - a) * 4);
              std::memcpy(Z + dst, h.z.data() + o, (from - a) * 4);
              std::memcpy(I + dst, h.ids.data() + o, (from - a) * 4);
            }
          }
        }
      });
  return true;
}

// Whether the cells' point-weighted mean population after inserting the m points is, by a
// strided sample of 16384 of them, more than 1.1x past `limit`: a sample cell's count a' of a
// cell's a new points is binomial(a, f), so sum 2 o a' / f + (sum a'^2 - (1 - f) s) / f^2
// estimates the growth of the squared populations' sum (o: the cell's stored points). Only for
// inserts of 4 samples or more; a borderline insert is counted exactly by the caller.
bool band_clearly_passed(const blockhash::Grid& g, const float* scaled, std::size_t m, double mean_before, double limit) {
  constexpr std::size_t kSample = 16384;
  if (m < 4 * kSample) return false;
  const std::size_t stride = m / kSample;
  // The sample's cells counted in an open-addressed table (a sort of the 16384 cells took 0.8 ms,
  // a tenth of a 10 % insert at 1M).
  constexpr std::size_t kSlots = 2 * kSample;
  constexpr std::uint32_t kFree = 0xffffffffu;
  static_assert(kSlots == std::size_t(1) << 15, "the hash below takes 15 bits");
  std::vector<std::uint32_t> key(kSlots, kFree), count(kSlots, 0);
  for (std::size_t i = 0; i < kSample; ++i) {
    const std::uint32_t c = cell_of(g.geom, scaled + 3 * (i * stride));
    std::size_t h = (std::uint64_t(c) * 0x9E3779B97F4A7C15ull) >> 49;  // 15 bits: kSlots
    while (key[h] != kFree && key[h] != c) h = (h + 1) & (kSlots - 1);
    key[h] = c;
    ++count[h];
  }
  const double f = double(kSample) / double(m);
  double cross = 0, sq = 0;
  for (std::size_t h = 0; h < kSlots; ++h) {
    if (key[h] == kFree) continue;
    const double a = double(count[h]), o = double(g.start(key[h] + 1) - g.start(key[h]));
    cross += 2 * o * a;
    sq += a * a;
  }
  const double grow = cross / f + (sq - (1 - f) * double(kSample)) / (f * f);
  const double n0 = double(g.n_points), mean = (mean_before * n0 + grow) / (n0 + double(m));
  return mean > 1.1 * limit;
}

}  // namespace

void GridIndex::insert_stored(const float*, const float* scaled, std::size_t n, std::int32_t first) {
  if (grid_build_mean_ <= 0) grid_build_mean_ = info_.mean_cell_points;  // the build's
  release_grid_views();  // the update writes the arrays; grid_upload_from makes them again
  // The new points' box, in one parallel pass (a serial test per point was a tenth of a 25 %
  // insert's rebuild): inside the grid's box when its corners are, and the live points' box
  // widened by it whichever way the insert goes (a rebuild takes it as the old points' box).
  const detail::PointScan ps = detail::scan_points(scaled, n, params_.threads);
  const bool in_box = inside(s_->grid->geom, ps.lo) && inside(s_->grid->geom, ps.hi);
  blockhash::widen_box(s_->grid->dbox, ps.lo[0], ps.lo[1], ps.lo[2]);
  blockhash::widen_box(s_->grid->dbox, ps.hi[0], ps.hi[1], ps.hi[2]);
  if (in_box) grid_insert(scaled, n, first);
  else grid_rebuild_live(scaled, n, first, false);
}

void GridIndex::remove_stored(const std::int32_t* ids, std::size_t n) {
  if (grid_build_mean_ <= 0) grid_build_mean_ = info_.mean_cell_points;  // the build's
  release_grid_views();
  grid_remove(ids, n);
}

void GridIndex::grid_positions() {
  const blockhash::Grid& g = *s_->grid;
  id_pos_.assign(std::size_t(id_bound()), -1);
  std::int32_t* const pos = id_pos_.data();
  const std::int32_t* const ids = g.ids.data();
  // In parallel: the ids are distinct, so no two writes meet.
  detail::parallel_for(g.n_points, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i)
      if (ids[i] != kHoleId) pos[std::size_t(ids[i])] = static_cast<std::int32_t>(i);
  });
}

void GridIndex::grid_upload_from(std::size_t point_from, std::size_t cell_from) {
  const blockhash::Grid& g = *s_->grid;
  const std::size_t pb = g.x.size() * 4, sb = g.starts.size() * 4;
  if (grid_in_place() || pb > g_points_cap_ || sb > g_starts_cap_ || g.occ.size() > g_occ_cap_ || !g_x_()) {
    upload_grid();  // reallocates what no longer fits, capacity grown by half
    return;
  }
  const auto& q = runtime_ptr()->queue();
  const std::size_t off = point_from * 4, len = pb - off;
  if (len > 0) {
    check_cl(q.enqueueWriteBuffer(g_x_, CL_FALSE, off, len, g.x.data() + point_from), "clEnqueueWriteBuffer", "blockhash grid x");
    check_cl(q.enqueueWriteBuffer(g_y_, CL_FALSE, off, len, g.y.data() + point_from), "clEnqueueWriteBuffer", "blockhash grid y");
    check_cl(q.enqueueWriteBuffer(g_z_, CL_FALSE, off, len, g.z.data() + point_from), "clEnqueueWriteBuffer", "blockhash grid z");
    check_cl(q.enqueueWriteBuffer(g_ids_, CL_FALSE, off, len, g.ids.data() + point_from), "clEnqueueWriteBuffer", "blockhash grid ids");
  }
  if (cell_from * 4 < sb)
    check_cl(q.enqueueWriteBuffer(g_starts_, CL_FALSE, cell_from * 4, sb - cell_from * 4, g.starts.data() + cell_from),
             "clEnqueueWriteBuffer", "blockhash grid cells");
  check_cl(q.enqueueWriteBuffer(g_occ_, CL_FALSE, 0, g.occ.size(), g.occ.data()), "clEnqueueWriteBuffer",
           "blockhash grid occupancy");
  check_cl(q.finish(), "clFinish", "blockhash grid update");
}

void GridIndex::grid_insert(const float* scaled, std::size_t m, std::int32_t first) {
  blockhash::Grid& g = *s_->grid;
  if (g.geom.sparse) {
    grid_insert_two_level(scaled, m, first);
    return;
  }
  if (info_.holes) grid_compact();
  const bhcl_grid_geom& geom = g.geom;
  const std::size_t nc = g.ncells(), n0 = g.n_points, n1 = n0 + m;
  // A large insert that a sample of it shows well past the band: one fresh build at once, without
  // the exact count below (a 25 % insert's count took a tenth of its rebuild). Only past an
  // eighth of the stored points: a smaller insert of the same distribution stays inside the
  // band (a tenth moves the mean by 9.6 %), and the count below is cheaper than the sample.
  if (8 * m >= n0 &&
      band_clearly_passed(g, scaled, m, info_.mean_cell_points, kRetuneAbove * std::max(1.0, grid_build_mean_))) {
    grid_rebuild_live(scaled, m, first, true);
    return;
  }
  // The new points' cells and a counting sort of them alone (stable: ascending ids in a cell),
  // in the build's scratch (sized for the build's points: no fresh pages), in parallel over T
  // ranges of the new points: each counts its cells, then scatters its points from its own
  // starts (the cells' starts plus the earlier ranges' counts). Per-range counts only where the
  // cells are not many more than the new points (a two-level-sized table stays serial).
  if (!g.scratch) g.scratch = std::make_shared<blockhash::GridScratch>();
  blockhash::GridScratch& sc = *g.scratch;
  if (sc.cell.size() < m) sc.cell.resize(m);
  if (sc.rec.size() < 4 * m) sc.rec.resize(4 * m);
  std::uint32_t* const cell = sc.cell.data();
  float* const rec = sc.rec.data();
  // A range per thread, handed out in turn (a thread that starts late on a shared machine takes
  // fewer). The per-range counts and the cells' new starts live in the scratch (kept with the
  // grid: the next insert faults in no fresh pages for them; before, two count tables per thread
  // were allocated, zeroed and faulted in anew by every insert).
  const unsigned T = nc <= 4 * m ? unsigned(std::max<std::size_t>(
                                       1, std::min<std::size_t>(params_.threads ? params_.threads : detail::default_threads(), m / 32768)))
                                 : 1u;
  if (sc.count.size() < std::size_t(T) * nc) sc.count.resize(std::size_t(T) * nc);
  std::uint32_t* const count = sc.count.data();
  std::fill_n(count, std::size_t(T) * nc, 0u);
  // Kept only where the cells are not many more than the points (a direct table of 8 cells per
  // point would keep 64 bytes per point between inserts); else freed after this insert.
  auto release_counts = [&] {
    if (nc > g.n_points) sc.count = blockhash::GridVec<std::uint32_t>(), sc.add = blockhash::GridVec<std::uint32_t>();
  };
  const bhcl_grid_geom gg = geom;  // in a local: the stores below would reload it through the reference
  detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      std::uint32_t* const ct = count + t * nc;
      const float* const P = scaled;
      std::uint32_t* const C = cell;
      for (std::size_t i = m * t / T, e = m * (t + 1) / T; i < e; ++i) {
        const std::uint32_t c = cell_of(gg, P + 3 * i);
        C[i] = c;
        ++ct[c];
      }
    }
  });
  sc.add.resize(nc + 1);
  std::uint32_t* const add = sc.add.data();  // add[c]: new points in cells < c
  add[0] = 0;
  std::size_t first_cell = nc;
  std::uint64_t sum2 = 0;  // in integers: a double's add chain bounded this loop
  std::size_t occupied = 0;
  std::vector<std::uint32_t> new_cells;  // empty before, holding points now (the pyramid's new bits)
  const std::uint32_t* const st = g.starts.data();
  for (std::size_t c = 0; c < nc; ++c) {
    std::uint32_t k = add[c];  // count[t][c] becomes range t's first slot of cell c
    for (unsigned t = 0; t < T; ++t) {
      const std::uint32_t a = count[t * nc + c];
      count[t * nc + c] = k;
      k += a;
    }
    add[c + 1] = k;
    const std::uint32_t old = st[c + 1] - st[c], a = k - add[c];
    const std::uint64_t v = std::uint64_t(old) + a;
    sum2 += v * v;
    occupied += v > 0 ? 1 : 0;
    if (old == 0 && a) new_cells.push_back(static_cast<std::uint32_t>(c));
    if (a && first_cell == nc) first_cell = c;
  }
  const double mean = double(sum2) / double(n1);
  // The leaf split: the cells have grown too full for the side tuned at the last full build.
  if (mean > kRetuneAbove * std::max(1.0, grid_build_mean_)) {
    release_counts();
    grid_rebuild_live(scaled, m, first, true);
    return;
  }
  detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      // Pointers in locals, the index stored as a float's bits by a plain store: a memcpy store
      // may alias anything and made every pointer reload per point.
      std::uint32_t* const at = count + t * nc;
      const float* const P = scaled;
      const std::uint32_t* const C = cell;
      float* const Rc = rec;
      for (std::size_t i = m * t / T, e = m * (t + 1) / T; i < e; ++i) {
        float* const r = Rc + 4 * std::size_t(at[C[i]]++);
        const std::uint32_t bits = static_cast<std::uint32_t>(i);
        float fb;
        std::memcpy(&fb, &bits, 4);
        r[0] = P[3 * i];
        r[1] = P[3 * i + 1];
        r[2] = P[3 * i + 2];
        r[3] = fb;
      }
    }
  });
  // An insert moves nearly every point: the id -> position map is dropped, and the next remove
  // (the one reader) makes it again in one parallel pass. Kept up to date here, its random
  // writes cost more than the merge itself.
  id_pos_.clear();
  // In place where the arrays have room (the build reserves an eighth more), else out of place
  // into the scratch arrays (room reserved there too), which then change places with the grid's.
  // Both in parallel over ranges of cells (the in-place backward pass they replace was serial:
  // half a fresh build's time for a 10 % insert).
  if (!merge_in_place(g, rec, m, first, add, first_cell)) {
    for (auto* v : {&sc.x, &sc.y, &sc.z}) reserve_with_room(*v, n1 + blockhash::kGridPad);
    reserve_with_room(sc.ids, n1 + blockhash::kGridPad);
    sc.x.resize(n1 + blockhash::kGridPad);
    sc.y.resize(n1 + blockhash::kGridPad);
    sc.z.resize(n1 + blockhash::kGridPad);
    sc.ids.resize(n1 + blockhash::kGridPad);
    merge_into_scratch(g, rec, m, first, add, first_cell, sc);
    std::swap(g.x, sc.x);
    std::swap(g.y, sc.y);
    std::swap(g.z, sc.z);
    std::swap(g.ids, sc.ids);
  }
  // The new starts, once every range has read the old ones.
  for (std::size_t c = first_cell; c < nc; ++c) g.starts[c] += add[c];
  g.starts[nc] = static_cast<std::uint32_t>(n1);
  for (std::size_t i = n1; i < n1 + blockhash::kGridPad; ++i) {
    g.x[i] = g.y[i] = g.z[i] = INFINITY;
    g.ids[i] = -1;
  }
  g.n_points = n1;
  s_->n_points = n1;
  const std::size_t p_from = first_cell < nc ? g.starts[first_cell] : n0;
  occupancy_add_cells(g, new_cells, m, params_.threads, [&](std::size_t cb, std::size_t ce, auto&& emit) {
    for (std::size_t c = std::max(cb, first_cell); c < ce; ++c)
      for (std::size_t j = add[c]; j < add[c + 1]; ++j) emit(std::uint32_t(c), rec[4 * j], rec[4 * j + 1], rec[4 * j + 2]);
  });
  grid_upload_from(p_from, first_cell);
  release_counts();
  info_.n_points = n1;
  info_.occupied_cells = occupied;
  info_.mean_cell_points = mean;
  ++info_.merges;
}

void GridIndex::grid_insert_two_level(const float* scaled, std::size_t m, std::int32_t first) {
  blockhash::Grid& g = *s_->grid;
  const std::size_t n0 = g.n_points, n1 = n0 + m;
  // The populations counted over the stored slots (holes included), as the build's mean is.
  const TwoLevelAdd add = two_level_additions(g, scaled, m, info_.mean_cell_points * double(n0), info_.occupied_cells);
  const double mean = add.sum2 / double(n1);
  const double entries = double(g.starts.size()) + double(add.new_segs.size()) * double(1u << BHCL_GRID_SEG_BITS);
  // Past the band (the leaf split), or a directory past its 2^31 entries: one fresh build.
  if (mean > kRetuneAbove * std::max(1.0, grid_build_mean_) || entries >= double(BHCL_GRID_EMPTY_SEG)) {
    grid_rebuild_live(scaled, m, first, true);
    return;
  }
  if (!g.scratch) g.scratch = std::make_shared<blockhash::GridScratch>();
  blockhash::GridScratch& sc = *g.scratch;
  sc.x.resize(n1 + blockhash::kGridPad);
  sc.y.resize(n1 + blockhash::kGridPad);
  sc.z.resize(n1 + blockhash::kGridPad);
  sc.ids.resize(n1 + blockhash::kGridPad);
  id_pos_.clear();  // nearly every point moves (as grid_insert's merge)
  merge_two_level_points(g, scaled, first, add, sc);
  const std::size_t p_from = g.start(std::size_t(add.key.front() >> 32));
  two_level_directory_in_place(g, add, params_.threads);
  std::swap(g.x, sc.x);
  std::swap(g.y, sc.y);
  std::swap(g.z, sc.z);
  std::swap(g.ids, sc.ids);
  for (std::size_t i = n1; i < n1 + blockhash::kGridPad; ++i) {
    g.x[i] = g.y[i] = g.z[i] = INFINITY;
    g.ids[i] = -1;
  }
  g.n_points = n1;
  s_->n_points = n1;
  occupancy_add_cells(g, add.new_cells, m, params_.threads, [&](std::size_t cb, std::size_t ce, auto&& emit) {
    auto k = std::lower_bound(add.key.begin(), add.key.end(), std::uint64_t(cb) << 32);
    for (; k != add.key.end() && (*k >> 32) < ce; ++k) {
      const float* const p = scaled + 3 * std::size_t(*k & 0xffffffffu);
      emit(std::uint32_t(*k >> 32), p[0], p[1], p[2]);
    }
  });
  grid_upload_from(p_from, 0);  // tables appended and moved starts anywhere in the directory: all of it
  info_.n_points = n1;
  info_.occupied_cells = add.occupied;
  info_.mean_cell_points = mean;
  info_.grid_directory_bytes = g.starts.size() * 4;
  ++info_.merges;
}

void GridIndex::grid_mark_holes_by_scan(const std::int32_t* ids, std::size_t n, std::size_t& lo, std::size_t& hi,
                                        unsigned& faces) {
  blockhash::Grid& g = *s_->grid;
  // The ids to remove are the marked ones that are still stored (earlier removes' ids are holes
  // or compacted away): the index's marks, a bit per id (set before remove_stored), read in place
  // of a byte per id made here (1 MB written, then read at random, at 1M ids).
  const std::uint32_t* const gone = removed_words();
  // Chunks handed out in turn (on a shared machine a thread that starts late takes fewer), each
  // noting the box's sides its removed points lay on: refit_box_faces redoes only those, from the
  // planes of cells at them. Taking every chunk's live box here read the three coordinate arrays
  // in full, 40-45 % of a 10 % remove (uniform 1M, 2.2-2.3 ms against a fresh build's 9.5).
  constexpr std::size_t kChunk = std::size_t(1) << 15;
  struct Part {
    std::size_t lo = SIZE_MAX, hi = 0, found = 0;
    unsigned faces = 0;
  };
  std::vector<Part> part((g.n_points + kChunk - 1) / kChunk);
  const bhcl_grid_dbox b = g.dbox;
  float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
  std::int32_t* const I = g.ids.data();
  detail::parallel_chunks(g.n_points, kChunk, params_.threads, [&](std::size_t c, std::size_t cb, std::size_t ce) {
    Part pt;  // in locals, written once: neighbouring parts share a cache line
    for (std::size_t i = cb; i < ce; ++i) {
      const std::int32_t id = I[i];
      if (id == kHoleId || !((gone[std::size_t(id) >> 5] >> (id & 31)) & 1u)) continue;
      pt.faces |= blockhash::box_faces_of(b, X[i], Y[i], Z[i]);
      X[i] = Y[i] = Z[i] = INFINITY;
      I[i] = kHoleId;
      pt.lo = std::min(pt.lo, i);
      pt.hi = i;
      ++pt.found;
    }
    part[c] = pt;
  });
  std::size_t found = 0;
  for (const Part& pt : part) {
    lo = std::min(lo, pt.lo);
    hi = std::max(hi, pt.hi);
    faces |= pt.faces;
    found += pt.found;
  }
  if (found != n) throw Error("blockhash: remove: " + std::to_string(n - found) + " of the ids are not stored (internal)");
  if (id_pos_.size() == std::size_t(id_bound()))  // a map kept (else made again when needed)
    for (std::size_t i = 0; i < n; ++i) id_pos_[std::size_t(ids[i])] = -1;
  else
    id_pos_.clear();
}

void GridIndex::grid_remove(const std::int32_t* ids, std::size_t n) {
  blockhash::Grid& g = *s_->grid;
  std::size_t lo = g.n_points, hi = 0;
  // The points' box (grid_search.h) stays the live points' own, as a load of the saved index
  // computes it: the sides a removed point lay on are refitted.
  unsigned faces = 0;
  // Many ids, or no id -> position map yet: one parallel pass over the stored ids against a mark
  // per id (sequential reads) is cheaper than making the map (a random write per point; 0.4-0.6x
  // of a fresh build for a 10 % remove). A few ids with the map: their slots directly.
  const bool have_map = id_pos_.size() == std::size_t(id_bound());
  if (n * 16 >= g.n_points || (!have_map && n * 256 >= g.n_points)) {
    grid_mark_holes_by_scan(ids, n, lo, hi, faces);
  } else {
    if (!have_map) grid_positions();
    for (std::size_t i = 0; i < n; ++i)
      if (id_pos_[std::size_t(ids[i])] < 0)
        throw Error("blockhash: remove: id " + std::to_string(ids[i]) + " is not stored (internal)");
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t p = std::size_t(id_pos_[std::size_t(ids[i])]);
      faces |= blockhash::box_faces_of(g.dbox, g.x[p], g.y[p], g.z[p]);
      g.x[p] = g.y[p] = g.z[p] = INFINITY;
      g.ids[p] = kHoleId;
      id_pos_[std::size_t(ids[i])] = -1;
      lo = std::min(lo, p);
      hi = std::max(hi, p);
    }
  }
  info_.holes += n;
  if (faces) blockhash::refit_box_faces(g, faces, params_.threads);
  // The live points' mean cell population, estimated as for a random thinning of the stored
  // ones (a Poisson cell of mean l thinned to f keeps a point-weighted mean of f l + 1); exact
  // again at the next compaction, merge or build. Without it the population could drift by the
  // 1/8 of holes a compaction waits for before the band below was looked at.
  const double f = double(g.n_points - info_.holes) / double(g.n_points);
  const double live_mean = 1.0 + (std::max(info_.mean_cell_points, 1.0) - 1.0) * f;
  // Too few points per cell for the tuned side: the leaf merge, a rebuild with a fresh side.
  if (live_mean < kRetuneBelow * grid_build_mean_) {
    grid_rebuild_live(nullptr, 0, 0, true);
    return;
  }
  if (8 * info_.holes > g.n_points) {
    grid_compact();
    if (info_.mean_cell_points < kRetuneBelow * grid_build_mean_) grid_rebuild_live(nullptr, 0, 0, true);
    return;
  }
  if (grid_in_place()) {
    upload_grid();  // the views again, over the arrays just written
    return;
  }
  // The holes in place: one write per array of the span they touch.
  const auto& q = runtime_ptr()->queue();
  const std::size_t off = lo * 4, len = (hi - lo + 1) * 4;
  check_cl(q.enqueueWriteBuffer(g_x_, CL_FALSE, off, len, g.x.data() + lo), "clEnqueueWriteBuffer", "blockhash grid x");
  check_cl(q.enqueueWriteBuffer(g_y_, CL_FALSE, off, len, g.y.data() + lo), "clEnqueueWriteBuffer", "blockhash grid y");
  check_cl(q.enqueueWriteBuffer(g_z_, CL_FALSE, off, len, g.z.data() + lo), "clEnqueueWriteBuffer", "blockhash grid z");
  check_cl(q.enqueueWriteBuffer(g_ids_, CL_FALSE, off, len, g.ids.data() + lo), "clEnqueueWriteBuffer", "blockhash grid ids");
  check_cl(q.finish(), "clFinish", "blockhash grid remove");
}

void GridIndex::grid_compact() {
  blockhash::Grid& g = *s_->grid;
  if (g.geom.sparse) {  // the two-level directory: a fresh build over the live points
    grid_rebuild_live(nullptr, 0, 0, false);
    info_.holes = 0;
    ++info_.compactions;
    return;
  }
  const std::size_t nc = g.ncells();
  std::size_t w = 0, first_moved = g.n_points;
  double sum2 = 0;
  std::size_t occupied = 0;
  for (std::size_t c = 0; c < nc; ++c) {
    const std::uint32_t s0 = g.starts[c], s1 = g.starts[c + 1];
    g.starts[c] = static_cast<std::uint32_t>(w);
    const std::size_t w0 = w;
    for (std::uint32_t i = s0; i < s1; ++i) {
      if (g.ids[i] == kHoleId) {
        first_moved = std::min<std::size_t>(first_moved, i);
        continue;
      }
      if (w != i) {
        g.x[w] = g.x[i];
        g.y[w] = g.y[i];
        g.z[w] = g.z[i];
        g.ids[w] = g.ids[i];
      }
      ++w;
    }
    const double v = double(w - w0);
    sum2 += v * v;
    occupied += w > w0 ? 1 : 0;
  }
  g.starts[nc] = static_cast<std::uint32_t>(w);
  g.x.resize(w + blockhash::kGridPad);
  g.y.resize(w + blockhash::kGridPad);
  g.z.resize(w + blockhash::kGridPad);
  g.ids.resize(w + blockhash::kGridPad);
  for (std::size_t i = w; i < w + blockhash::kGridPad; ++i) {
    g.x[i] = g.y[i] = g.z[i] = INFINITY;
    g.ids[i] = -1;
  }
  g.n_points = w;
  s_->n_points = w;
  info_.n_points = w;
  info_.holes = 0;
  info_.occupied_cells = occupied;
  info_.mean_cell_points = w ? sum2 / double(w) : 0;
  ++info_.compactions;
  if (id_pos_.size() != std::size_t(id_bound())) grid_positions();
  else
    for (std::size_t i = std::min(first_moved, w); i < w; ++i) id_pos_[std::size_t(g.ids[i])] = static_cast<std::int32_t>(i);
  // The cell table changes from the first cell holding a hole on; simplest to write it whole.
  blockhash::build_grid_occupancy(g, params_.threads);  // cells emptied (the live box is as it was)
  grid_upload_from(std::min(first_moved, w), 0);
}

// The live points of g (holes dropped) into x, y, z, ids, in the grid's own order (cell by cell):
// two sequential parallel passes over the slots, the live ones per range, then the copy. An
// id-ordered gather went through the id -> slot map, a random write and a random read per point:
// as long as the build itself (47 of 100 ms, 1.25M points). So after such a rebuild a cell's
// slots follow the old grid's order, not ascending ids: exact answers are unchanged (the kernels
// rank by distance, then id); a budgeted query may examine other points of a cell its budget
// cuts into than a fresh build's would, as any input order does.
static void grid_live_in_cell_order(const blockhash::Grid& g, blockhash::GridVec<float>& x, blockhash::GridVec<float>& y,
                                    blockhash::GridVec<float>& z, blockhash::GridVec<std::int32_t>& ids) {
  const std::size_t n = g.n_points;
  const unsigned T = std::max(1u, std::min<unsigned>(detail::default_threads(), unsigned(n / 65536 + 1)));
  std::vector<std::size_t> count(T + 1, 0);
  const std::size_t per = (n + T - 1) / T;
  const std::int32_t* const gid = g.ids.data();
  detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t)
      for (std::size_t i = t * per, e = std::min(n, i + per); i < e; ++i) count[t + 1] += gid[i] != kHoleId;
  });
  for (unsigned t = 0; t < T; ++t) count[t + 1] += count[t];
  x.resize(count[T]);
  y.resize(count[T]);
  z.resize(count[T]);
  ids.resize(count[T]);
  detail::parallel_chunks(T, 1, T, [&](std::size_t, std::size_t tb, std::size_t te) {
    for (std::size_t t = tb; t < te; ++t) {
      std::size_t w = count[t];
      for (std::size_t i = t * per, e = std::min(n, i + per); i < e; ++i) {
        if (gid[i] == kHoleId) continue;
        x[w] = g.x[i];
        y[w] = g.y[i];
        z[w] = g.z[i];
        ids[w++] = gid[i];
      }
    }
  });
}

// Room to grow where an insert left the grid's box (a sensor moving on: every scan's leading edge
// lies outside the box its map was built in, and each such insert was a full build). For each
// axis and side the new points passed, the box of the rebuild is extended by half the points'
// extent there, through two points at the corners of that box appended to the build's input with
// the hole id; after the build they become holes (+inf), so they are never returned and the live
// points' box stays their own. The next inserts that land in the room merge. Returns the points
// appended (0 or 2).
static std::size_t add_growth_room(const blockhash::Grid& g, const detail::PointScan& extra_box, std::size_t m,
                                   blockhash::GridVec<float>& pts, blockhash::GridVec<std::int32_t>& ids) {
  if (m == 0) return 0;
  double lo[3], hi[3];
  const bhcl_grid_dbox& b = g.dbox;
  const double blo[3] = {b.lx, b.ly, b.lz}, bhi[3] = {b.hx, b.hy, b.hz};
  const double o[3] = {g.geom.ox, g.geom.oy, g.geom.oz}, nc[3] = {double(g.geom.nx), double(g.geom.ny), double(g.geom.nz)};
  double glo[3], ghi[3];
  for (int d = 0; d < 3; ++d) {
    lo[d] = std::isfinite(blo[d]) ? blo[d] : INFINITY;
    hi[d] = std::isfinite(bhi[d]) ? bhi[d] : -INFINITY;
    glo[d] = o[d];
    ghi[d] = o[d] + nc[d] * double(g.geom.h);
  }
  const double nlo[3] = {extra_box.lo[0], extra_box.lo[1], extra_box.lo[2]};
  const double nhi[3] = {extra_box.hi[0], extra_box.hi[1], extra_box.hi[2]};
  const double cell = double(g.geom.h);
  float c0[3], c1[3];
  bool room = false;
  for (int d = 0; d < 3; ++d) {
    const double l = std::min(lo[d], nlo[d]), h = std::max(hi[d], nhi[d]), ext = h - l;
    // Past the box: half the extent of room. Room left by an earlier rebuild is kept where the
    // new points still reach the front on that side (within a quarter of the extent of it: a
    // rebuild for the band must not take away the moving window's room), however much of it the
    // window has used: room is what lies past the build's own slack (under a cell per axis), so
    // past two cells (a quarter of the extent here dropped room half used, and the next scan
    // rebuilt again).
    const double kept = 2.0 * cell;
    double c_lo = l, c_hi = h;
    if (nlo[d] < glo[d]) c_lo = l - 0.5 * ext;
    else if (glo[d] < l - kept && nlo[d] < l + ext / 4) c_lo = glo[d];
    if (nhi[d] > ghi[d]) c_hi = h + 0.5 * ext;
    else if (ghi[d] > h + kept && nhi[d] > h - ext / 4) c_hi = ghi[d];
    room = room || c_lo < l || c_hi > h;
    c0[d] = static_cast<float>(c_lo);
    c1[d] = static_cast<float>(c_hi);
    if (!std::isfinite(c0[d]) || !std::isfinite(c1[d])) return 0;  // at the float range's edge: no room
  }
  if (!room) return 0;
  pts.insert(pts.end(), c0, c0 + 3);
  pts.insert(pts.end(), c1, c1 + 3);
  ids.push_back(kHoleId);
  ids.push_back(kHoleId);
  return 2;
}

void GridIndex::grid_rebuild_live(const float* extra, std::size_t m, std::int32_t first, bool retune) {
  // A fresh build over the live points and the new ones, with the build's own parameters (a
  // tuned side unless the caller fixed one), done once (issue 39: before, a rebuild that kept the
  // side and then found the cells outside the band built a second time: 3.5-4.5x a fresh build
  // across the band). The build reads the old grid's arrays where they are (a gather of a copy,
  // then a pass mapping the build's indices to ids, made it 2.1x), the new points and the room's
  // corners behind them; with holes, the live points are gathered first (holes dropped).
  blockhash::Grid& g = *s_->grid;
  // The room's corners first (into `room`, with the hole id); the new points are read where they
  // are, their ids first + i, unless corners must follow them (then a copy with the corners).
  blockhash::GridVec<float> room;
  blockhash::GridVec<std::int32_t> room_ids;
  const std::size_t phantoms = m ? add_growth_room(g, detail::scan_points(extra, m, params_.threads), m, room, room_ids) : 0;
  blockhash::GridVec<float> add;
  blockhash::GridVec<std::int32_t> add_ids;
  if (phantoms) {
    add.assign(extra, extra + 3 * m);
    add.insert(add.end(), room.begin(), room.end());
    add_ids.resize(m);
    for (std::size_t i = 0; i < m; ++i) add_ids[i] = first + static_cast<std::int32_t>(i);
    add_ids.insert(add_ids.end(), room_ids.begin(), room_ids.end());
  }
  blockhash::GridInput in;
  // A box holding every live point: the live points' box (a remove does not shrink it), or where
  // it is unset, theirs computed.
  bhcl_grid_dbox box = g.dbox;
  if (!(std::isfinite(box.lx) && std::isfinite(box.ly) && std::isfinite(box.lz) && std::isfinite(box.hx) &&
        std::isfinite(box.hy) && std::isfinite(box.hz)))
    box = blockhash::grid_points_box(g, params_.threads);
  const float lo[3] = {box.lx, box.ly, box.lz}, hi[3] = {box.hx, box.hy, box.hz};
  for (int d = 0; d < 3; ++d) in.soa_lo[d] = lo[d], in.soa_hi[d] = hi[d];
  blockhash::GridVec<float> ox, oy, oz;
  blockhash::GridVec<std::int32_t> oids;
  // The old arrays' memory is the new arrays' where it fits (issue 39): once the build's first
  // pass has read the input into its records, the old arrays go back into g where they hold the
  // result with an eighth to spare (the next insert's merge in place) and at most twice over (a
  // large remove's rebuild gives its memory back), and the build writes its points there. A
  // rebuild of about the old size (a scan past the box's edge, a remove below the band) then
  // faults in no fresh pages; freed and allocated again, the arrays' pages were faulted in
  // afresh wherever the allocator gave fresh ones (a third of a 1M rebuild's time).
  blockhash::GridVec<float> hx, hy, hz;
  blockhash::GridVec<std::int32_t> hids;
  const std::size_t old_cap = std::min({g.x.capacity(), g.y.capacity(), g.z.capacity(), g.ids.capacity()}),
                    old_max = std::max({g.x.capacity(), g.y.capacity(), g.z.capacity(), g.ids.capacity()});
  if (info_.holes) {  // the live points copied out, the old arrays held until the copy is read
    grid_live_in_cell_order(g, ox, oy, oz, oids);
    hx = std::move(g.x), hy = std::move(g.y), hz = std::move(g.z), hids = std::move(g.ids);
  } else {  // moved out and read where they are
    ox = std::move(g.x), oy = std::move(g.y), oz = std::move(g.z), oids = std::move(g.ids);
    oids.resize(g.n_points);  // the pad not read
  }
  if (g.scratch) {  // an insert's merge arrays; the build's cells and records are kept
    g.scratch->x = blockhash::GridVec<float>();
    g.scratch->y = blockhash::GridVec<float>();
    g.scratch->z = blockhash::GridVec<float>();
    g.scratch->ids = blockhash::GridVec<std::int32_t>();
  }
  in.x = ox.data(), in.y = oy.data(), in.z = oz.data(), in.soa_ids = oids.data(), in.n_soa = oids.size();
  const std::size_t need = oids.size() + (phantoms ? add_ids.size() : m) + blockhash::kGridPad;
  const bool old_arrays_kept = old_cap >= need + need / 8 && old_max <= 2 * need;
  // Where the old arrays will not hold the result (an insert past the band grows them), the build
  // reads them twice, in their cell order (no records: grid_build.cpp's count_from_cells), and they are freed
  // after; where they will, they go back into g before the build writes there.
  in.soa_in_cells = !old_arrays_kept;
  in.release = [&] {  // read by the build's first pass: back into g (or freed) before it sizes the new arrays
    if (info_.holes) {
      ox = blockhash::GridVec<float>(), oy = blockhash::GridVec<float>(), oz = blockhash::GridVec<float>();
      oids = blockhash::GridVec<std::int32_t>();
    } else {
      hx = std::move(ox), hy = std::move(oy), hz = std::move(oz), hids = std::move(oids);
    }
    if (old_arrays_kept) g.x = std::move(hx), g.y = std::move(hy), g.z = std::move(hz), g.ids = std::move(hids);
    hx = blockhash::GridVec<float>(), hy = blockhash::GridVec<float>(), hz = blockhash::GridVec<float>();
    hids = blockhash::GridVec<std::int32_t>();
  };
  if (phantoms) in.xyz = add.data(), in.aos_ids = add_ids.data(), in.n_aos = add_ids.size();
  else in.xyz = extra, in.aos_first = first, in.n_aos = m;
  const blockhash::UpdateCounters keep(info_);
  const double side_before = info_.cell_size;
  id_pos_.clear();  // every point moves; the next remove that needs the map makes it again
  const std::size_t builds_before = grid_builds_;
  // In the structure's coordinates and scale (an update does not rescale), from points known
  // finite: no validation or scale pass, the live ids stored by the build itself.
  build_scaled(in, params_.cell_size);
  if (phantoms) {  // the corners of the room left become holes
    detail::parallel_for(g.n_points, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i)
        if (g.ids[i] == kHoleId) g.x[i] = g.y[i] = g.z[i] = INFINITY;
    });
  }
  if (phantoms) {
    g.dbox = blockhash::grid_points_box(g, params_.threads);  // the live points' own
    // The build's node boxes held the room's corners; those of the nodes holding them made again
    // without them (tight boxes are what make the far walk skip; loose ones stay exact). The
    // pyramid's bits stay (a cell of holes stays marked): the whole pyramid built a second time
    // read every point again.
    std::vector<std::uint32_t> corner_cells;
    for (std::size_t k = 0; k < phantoms; ++k) corner_cells.push_back(cell_of(g.geom, room.data() + 3 * k));
    blockhash::refresh_node_boxes(g, corner_cells);
  }
  // The build uploaded the arrays with their ids; only the holes made above are new (a view
  // shows the host array itself).
  if (phantoms && !grid_in_place()) {
    const auto& q = runtime_ptr()->queue();
    const std::size_t bytes = g.ids.size() * 4;
    check_cl(q.enqueueWriteBuffer(g_x_, CL_FALSE, 0, bytes, g.x.data()), "clEnqueueWriteBuffer", "blockhash grid x");
    check_cl(q.enqueueWriteBuffer(g_y_, CL_FALSE, 0, bytes, g.y.data()), "clEnqueueWriteBuffer", "blockhash grid y");
    check_cl(q.enqueueWriteBuffer(g_z_, CL_FALSE, 0, bytes, g.z.data()), "clEnqueueWriteBuffer", "blockhash grid z");
    check_cl(q.enqueueWriteBuffer(g_occ_, CL_FALSE, 0, g.occ.size(), g.occ.data()), "clEnqueueWriteBuffer",
             "blockhash grid occupancy");
    check_cl(q.enqueueWriteBuffer(g_ids_, CL_TRUE, 0, bytes, g.ids.data()), "clEnqueueWriteBuffer", "blockhash grid ids");
  }
  keep.put(info_);
  info_.holes = phantoms;
  info_.update_rebuilds += grid_builds_ - builds_before;  // the builds made, not the calls
  if (retune || info_.cell_size != side_before) ++info_.retunes;
  // Every rebuild is a fresh build: its population is the one the band is measured from.
  grid_build_mean_ = info_.mean_cell_points;
}

// Saved and loaded after updates (grid_io.cpp's version 3, io.cpp's version 5): the ids issued,
// the holes where they are, the population the retune band is measured from and the counters, so
// that a loaded index answers as the saved one and its next updates continue where it stopped.
blockhash::GridIdState GridIndex::grid_update_state() const {
  blockhash::GridIdState st;
  st.id_bound = id_bound();
  st.tuned_mean = grid_build_mean_ > 0 ? grid_build_mean_ : 0.0;
  st.merges = info_.merges;
  st.compactions = info_.compactions;
  st.update_rebuilds = info_.update_rebuilds;
  st.retunes = info_.retunes;
  return st;
}

void GridIndex::loaded_update_state(const blockhash::GridIdState& st) {
  info_.merges = st.merges;
  info_.compactions = st.compactions;
  info_.update_rebuilds = st.update_rebuilds;
  info_.retunes = st.retunes;
  info_.holes = st.holes;
  if (st.tuned_mean > 0) grid_build_mean_ = st.tuned_mean;
  s_->info = info_;
  const blockhash::Grid& g = *s_->grid;
  if (st.holes == 0 && std::size_t(st.id_bound) == g.n_points) return;  // ids 0 .. N - 1
  std::vector<std::int32_t> live;
  live.reserve(st.live);
  for (std::size_t i = 0; i < g.n_points; ++i)
    if (g.ids[i] != kHoleId) live.push_back(g.ids[i]);
  std::sort(live.begin(), live.end());
  set_id_state(static_cast<std::int32_t>(st.id_bound), live);
}

}  // namespace bhcl
