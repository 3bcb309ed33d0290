// Block hashing, grid layout: the occupancy pyramid (kernels/grid_search.h) from the directory,
// and its nodes' point boxes from the cells' points.
// Built from the cells' runs rather than from the points, so it holds after inserts, removes and
// loads alike; a cell whose points were all removed stays marked until the compaction (its holes
// still fill its run), which costs a look, never a point.
#include <algorithm>
#include <cstring>
#include <vector>

#include "bhcl_shared.h"
#include "blockhash/grid.hpp"
#include "core/parallel.hpp"

namespace bhcl::blockhash {
namespace {

// Calls fn(x, a, b) for each cell x of row (y, z) whose run [a, b) is not empty, through either
// directory (a two-level directory's empty segment skipped 16 cells at once).
template <class Fn>
void for_each_run(const Grid& g, std::size_t y, std::size_t z, Fn&& fn) {
  const std::size_t nx = g.geom.nx;
  const std::uint32_t* const st = g.starts.data();
  constexpr std::size_t kSeg = std::size_t(1) << BHCL_GRID_SEG_BITS;
  std::size_t c = (z * g.geom.ny + y) * nx;
  if (!g.geom.sparse) {
    for (std::size_t x = 0; x < nx; ++x, ++c)
      if (st[c + 1] > st[c]) fn(x, st[c], st[c + 1]);
    return;
  }
  std::uint32_t a = g.start(c);
  for (std::size_t x = 0; x < nx;) {
    if ((c & (kSeg - 1)) == 0 && x + kSeg <= nx && (st[c >> BHCL_GRID_SEG_BITS] & BHCL_GRID_EMPTY_SEG)) {
      x += kSeg, c += kSeg;
      a = g.start(c);
      continue;
    }
    const std::uint32_t b = g.start(c + 1);
    if (b > a) fn(x, a, b);
    a = b;
    ++x, ++c;
  }
}

// Level 1 from the fine cells, row by row: one task per level-1 z index, which owns those bytes.
void occupancy_level1(const Grid& g, std::uint8_t* occ, unsigned threads) {
  const bhcl_grid_geom& gm = g.geom;
  const std::size_t ny = gm.ny, nz = gm.nz;
  const std::size_t dx = bhcl_grid_occ_dim(gm.nx, 1), dy = bhcl_grid_occ_dim(gm.ny, 1);
  detail::parallel_for(
      bhcl_grid_occ_dim(gm.nz, 1),
      [&](std::size_t zb, std::size_t ze) {
        std::fill(occ + zb * dx * dy, occ + ze * dx * dy, std::uint8_t(0));
        for (std::size_t z = 2 * zb; z < std::min(2 * ze, nz); ++z)
          for (std::size_t y = 0; y < ny; ++y) {
            std::uint8_t* const row = occ + ((z >> 1) * dy + (y >> 1)) * dx;
            const unsigned yz = unsigned(((y & 1) << 1) | ((z & 1) << 2));
            for_each_run(g, y, z, [&](std::size_t x, std::uint32_t, std::uint32_t) {
              row[x >> 1] |= std::uint8_t(1u << ((x & 1) | yz));
            });
          }
      },
      threads, 8);
}

constexpr bhcl_grid_dbox kEmptyBox{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};

// Box n widened by the live points of slots [a, b). Holes (+inf in every coordinate; none in a
// fresh build, Holes false) left out by a select: the minima take +inf as it is, the maxima see
// -inf. In registers, through local pointers: widened in place, the box could alias the points
// and was stored and reloaded at every point.
template <bool Holes = true>
inline void widen_by_slots(bhcl_grid_dbox& box, const Grid& g, std::uint32_t a, std::uint32_t b) {
  const float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
  bhcl_grid_dbox n = box;
  for (std::uint32_t i = a; i < b; ++i) {
    const float px = X[i], py = Y[i], pz = Z[i];
    const bool live = !Holes || px < INFINITY;
    n.lx = std::min(n.lx, px), n.ly = std::min(n.ly, py), n.lz = std::min(n.lz, pz);
    n.hx = std::max(n.hx, live ? px : -INFINITY), n.hy = std::max(n.hy, live ? py : -INFINITY);
    n.hz = std::max(n.hz, live ? pz : -INFINITY);
  }
  box = n;
}

// The box of a fresh build's points (no holes) of slots [a, b), four at a time (GCC and Clang
// vector extensions: SSE on x86-64, NEON on ARM): the points of a level-2 node's row of 4 cells
// are adjacent, 28 on average for Cornell 1M, where the widening point by point took 19
// instructions a point (box gathered during the placement, callgrind: 36M a build).
using V4 = float __attribute__((vector_size(16)));
inline V4 load4(const float* p) {
  V4 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline V4 vmin(V4 a, V4 b) { return a < b ? a : b; }
inline V4 vmax(V4 a, V4 b) { return a > b ? a : b; }
inline float hmin(V4 v) { return std::min(std::min(v[0], v[1]), std::min(v[2], v[3])); }
inline float hmax(V4 v) { return std::max(std::max(v[0], v[1]), std::max(v[2], v[3])); }
void widen_by_slots_fresh(bhcl_grid_dbox& box, const Grid& g, std::uint32_t a, std::uint32_t b) {
  if (b - a < 4) {
    widen_by_slots<false>(box, g, a, b);
    return;
  }
  const float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
  V4 lx = load4(X + a), ly = load4(Y + a), lz = load4(Z + a);
  V4 hx = lx, hy = ly, hz = lz;
  auto take = [&](std::uint32_t i) {
    const V4 x = load4(X + i), y = load4(Y + i), z = load4(Z + i);
    lx = vmin(lx, x), ly = vmin(ly, y), lz = vmin(lz, z);
    hx = vmax(hx, x), hy = vmax(hy, y), hz = vmax(hz, z);
  };
  std::uint32_t i = a + 4;
  for (; i + 4 <= b; i += 4) take(i);
  if (i < b) take(b - 4);  // the last four again with the tail: a minimum does not mind
  box.lx = std::min(box.lx, hmin(lx)), box.ly = std::min(box.ly, hmin(ly)), box.lz = std::min(box.lz, hmin(lz));
  box.hx = std::max(box.hx, hmax(hx)), box.hy = std::max(box.hy, hmax(hy)), box.hz = std::max(box.hz, hmax(hz));
}

// Calls fn(X, m, a, b) for each level-2 segment X of row (y, z) (its cells 4X .. 4X + 3) that
// holds a run: m has bit j set when cell 4X + j's run is not empty, [a, b) is the segment's slots
// (its cells' runs are adjacent). A direct directory reads two entries to skip an empty segment.
template <class Fn>
void for_each_segment(const Grid& g, std::size_t y, std::size_t z, Fn&& fn) {
  const std::size_t nx = g.geom.nx, row = (z * g.geom.ny + y) * nx;
  if (!g.geom.sparse) {
    const std::uint32_t* const st = g.starts.data() + row;
    for (std::size_t x0 = 0; x0 < nx; x0 += 4) {
      const std::size_t x1 = std::min(nx, x0 + 4);
      if (st[x1] == st[x0]) continue;
      unsigned m = 0;
      for (std::size_t x = x0; x < x1; ++x) m |= unsigned(st[x + 1] > st[x]) << (x - x0);
      fn(x0 >> 2, m, st[x0], st[x1]);
    }
    return;
  }
  std::size_t X = SIZE_MAX;
  unsigned m = 0;
  std::uint32_t sa = 0, sb = 0;
  for_each_run(g, y, z, [&](std::size_t x, std::uint32_t a, std::uint32_t b) {
    if ((x >> 2) != X) {
      if (m) fn(X, m, sa, sb);
      X = x >> 2, m = 0, sa = a;
    }
    m |= 1u << (x & 3);
    sb = b;
  });
  if (m) fn(X, m, sa, sb);
}

// Levels 1 and 2 of g's pyramid in g.occ (sized): level 1's bytes from byte 0, level 2's after
// them, level 2's boxes first at the boxes' offset (loaded and stored through memcpy: occ is bytes).
struct Levels12 {
  std::size_t d1x, d1y, d1z, dx, dy, dz;
  std::uint8_t *l1, *l2, *box2;
  explicit Levels12(Grid& g)
      : d1x(bhcl_grid_occ_dim(g.geom.nx, 1)), d1y(bhcl_grid_occ_dim(g.geom.ny, 1)), d1z(bhcl_grid_occ_dim(g.geom.nz, 1)),
        dx(bhcl_grid_occ_dim(g.geom.nx, 2)), dy(bhcl_grid_occ_dim(g.geom.ny, 2)), dz(bhcl_grid_occ_dim(g.geom.nz, 2)) {
    std::uint32_t top_off = 0, total = 0;
    bhcl_grid_occ_top(g.geom, &top_off, &total);
    l1 = g.occ.data();
    l2 = l1 + d1x * d1y * d1z;
    box2 = l1 + bhcl_grid_tbox_off(total);
  }
  // Fine row (y, z): its first level-1 byte, its cells' bit at an even x (the bit at x odd is the
  // next one), its first level-2 node.
  std::size_t row1(std::size_t y, std::size_t z) const { return ((z >> 1) * d1y + (y >> 1)) * d1x; }
  static unsigned row_bit1(std::size_t y, std::size_t z) { return 1u << (((y & 1) << 1) | ((z & 1) << 2)); }
  std::size_t row2(std::size_t y, std::size_t z) const { return ((z >> 2) * dy + (y >> 2)) * dx; }
  bhcl_grid_dbox box(std::size_t i) const {
    bhcl_grid_dbox b;
    std::memcpy(&b, box2 + i * sizeof(b), sizeof(b));
    return b;
  }
  void set_box(std::size_t i, const bhcl_grid_dbox& b) const { std::memcpy(box2 + i * sizeof(b), &b, sizeof(b)); }
  // Level 2's boxes of z indices [zb, ze) emptied (inverted).
  void empty_boxes(std::size_t zb, std::size_t ze) const {
    for (std::size_t i = zb * dx * dy; i < ze * dx * dy; ++i) set_box(i, kEmptyBox);
  }
  // Level 1's bytes (zero before) and level 2's boxes (empty before) of level-2 z indices [zb, ze)
  // from the directory and the points, a pass over each.
  void from_cells(const Grid& g, std::size_t zb, std::size_t ze) const {
    for (std::size_t z = 4 * zb; z < std::min<std::size_t>(4 * ze, g.geom.nz); ++z)
      for (std::size_t y = 0; y < g.geom.ny; ++y) {
        std::uint8_t* const bytes = l1 + row1(y, z);
        const unsigned yz = row_bit1(y, z);
        const std::size_t nodes = row2(y, z);
        for_each_segment(g, y, z, [&](std::size_t s, unsigned m, std::uint32_t a, std::uint32_t b) {
          bytes[2 * s] |= std::uint8_t((m & 3u) * yz);  // cells 4s, 4s + 1: x bits 0 and 1
          if (m >> 2) bytes[2 * s + 1] |= std::uint8_t((m >> 2) * yz);
          bhcl_grid_dbox n = box(nodes + s);
          widen_by_slots(n, g, a, b);
          set_box(nodes + s, n);
        });
      }
  }
  // Level 2's bytes of z indices [zb, ze) from level 1's (a child's bit set when its byte is not 0):
  // levels_above2's rule for the levels above, written out for level 2 because from_children's
  // per-child lambdas made level 2 of Cornell 1M 0.4 ms slower (53k nodes; tried in session 13).
  void bits2(std::size_t zb, std::size_t ze) const {
    for (std::size_t Z = zb; Z < ze; ++Z)
      for (std::size_t Y = 0; Y < dy; ++Y)
        for (std::size_t X = 0; X < dx; ++X) {
          unsigned m = 0;
          for (unsigned o = 0; o < 8; ++o) {
            const std::size_t x = 2 * X + (o & 1), y = 2 * Y + ((o >> 1) & 1), z = 2 * Z + (o >> 2);
            if (x < d1x && y < d1y && z < d1z && l1[(z * d1y + y) * d1x + x]) m |= 1u << o;
          }
          l2[(Z * dy + Y) * dx + X] = std::uint8_t(m);
        }
  }
};

// Each node of level l from its (up to 8) children of level l - 1: put(node, make(child_at)),
// where child_at(o) is the index in level l - 1 of child o (bit 0: x, 1: y, 2: z) or -1 past the
// grid's edge. One task per level-l z index, which owns those nodes; threads only for levels of
// 64k nodes or more (a thread's start, about 20 us here, costs more than a small level: levels
// 2 and up of Cornell 1M, 53k nodes and less, took 0.6 ms on 2 threads).
template <class Put, class Make>
void from_children(const bhcl_grid_geom& gm, std::uint32_t l, unsigned threads, Put&& put, Make&& make) {
  const std::size_t cx = bhcl_grid_occ_dim(gm.nx, l - 1), cy = bhcl_grid_occ_dim(gm.ny, l - 1);
  const std::size_t cz = bhcl_grid_occ_dim(gm.nz, l - 1);
  const std::size_t dx = bhcl_grid_occ_dim(gm.nx, l), dy = bhcl_grid_occ_dim(gm.ny, l);
  detail::parallel_for(
      bhcl_grid_occ_dim(gm.nz, l),
      [&](std::size_t zb, std::size_t ze) {
        for (std::size_t Z = zb; Z < ze; ++Z)
          for (std::size_t Y = 0; Y < dy; ++Y)
            for (std::size_t X = 0; X < dx; ++X) {
              auto child_at = [&](unsigned o) -> std::ptrdiff_t {
                const std::size_t x = 2 * X + (o & 1), y = 2 * Y + ((o >> 1) & 1), z = 2 * Z + (o >> 2);
                return x < cx && y < cy && z < cz ? std::ptrdiff_t((z * cy + y) * cx + x) : -1;
              };
              put((Z * dy + Y) * dx + X, make(child_at));
            }
      },
      threads, std::max<std::size_t>(1, (std::size_t(1) << 16) / (dx * dy)));
}

// Levels 3 .. top, bits and boxes, from level 2's (g.occ holding levels 1 and 2 and their boxes).
void levels_above2(Grid& g, std::uint32_t top, unsigned threads) {
  const bhcl_grid_geom& gm = g.geom;
  std::uint8_t* const occ = g.occ.data();
  const Levels12 lv(g);
  std::size_t off = bhcl_grid_occ_size(gm, 1), at = 0;  // level l - 1's first byte, first box
  for (std::uint32_t l = 3; l <= top; ++l) {
    const std::size_t below = bhcl_grid_occ_size(gm, l - 1);
    const std::uint8_t* const bits = occ + off;
    from_children(
        gm, l, threads, [&](std::size_t i, std::uint8_t m) { occ[off + below + i] = m; },
        [&](auto child_at) {
          unsigned m = 0;
          for (unsigned o = 0; o < 8; ++o)
            if (const std::ptrdiff_t i = child_at(o); i >= 0 && bits[i]) m |= 1u << o;
          return std::uint8_t(m);
        });
    from_children(
        gm, l, threads, [&](std::size_t i, const bhcl_grid_dbox& b) { lv.set_box(at + below + i, b); },
        [&](auto child_at) {
          bhcl_grid_dbox b = kEmptyBox;
          for (unsigned o = 0; o < 8; ++o)
            if (const std::ptrdiff_t i = child_at(o); i >= 0) unite_box(b, lv.box(at + std::size_t(i)));
          return b;
        });
    off += below;
    at += below;
  }
}

// g.occ sized and zeroed for g's geometry; the top level.
std::uint32_t start_pyramid(Grid& g) {
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(g.geom, &top_off, &total);
  g.occ.assign(bhcl_grid_occ_bytes(g.geom), std::uint8_t(0));  // the boxes' padding zeroed too
  return top;
}

// The box of points [b, e) of one coordinate array, holes (+inf) left out: lanes of 16 points
// without branches, so that it vectorises (a hole is +inf: the minima take it as it is, the
// maxima skip it). The per-point test and widen it replaces took 3 ms at 1M points.
void extent_live(const float* v, std::size_t b, std::size_t e, float& lo, float& hi) {
  constexpr std::size_t kLanes = 16;
  float l[kLanes], h[kLanes];
  for (std::size_t j = 0; j < kLanes; ++j) l[j] = lo, h[j] = hi;
  std::size_t i = b;
  for (; i + kLanes <= e; i += kLanes)
    for (std::size_t j = 0; j < kLanes; ++j) {
      const float x = v[i + j], live = x < INFINITY ? x : -INFINITY;  // selects, not branches
      l[j] = x < l[j] ? x : l[j];
      h[j] = live > h[j] ? live : h[j];
    }
  for (; i < e; ++i) {
    l[0] = v[i] < l[0] ? v[i] : l[0];
    h[0] = v[i] > h[0] && v[i] < INFINITY ? v[i] : h[0];
  }
  for (std::size_t j = 0; j < kLanes; ++j) lo = std::min(lo, l[j]), hi = std::max(hi, h[j]);
}

// b widened to hold the live points of slots [begin, end) (holes left out), vectorised.
void widen_box_live(const Grid& g, std::size_t begin, std::size_t end, bhcl_grid_dbox& b) {
  extent_live(g.x.data(), begin, end, b.lx, b.hx);  // holes are +inf in every coordinate
  extent_live(g.y.data(), begin, end, b.ly, b.hy);
  extent_live(g.z.data(), begin, end, b.lz, b.hz);
}

}  // namespace

std::size_t grid_occupancy_bytes(const bhcl_grid_geom& g) { return bhcl_grid_occ_bytes(g); }

// The box of the live points (holes, at +inf in every coordinate, left out).
bhcl_grid_dbox grid_points_box(const Grid& g, unsigned threads) {
  const std::size_t n = g.n_points;
  if (n == 0) return bhcl_grid_dbox{-INFINITY, -INFINITY, -INFINITY, INFINITY, INFINITY, INFINITY};
  const unsigned parts = std::max(1u, std::min(threads ? threads : detail::default_threads(), 64u));
  std::vector<bhcl_grid_dbox> part(parts, bhcl_grid_dbox{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY});
  detail::parallel_for(
      parts,
      [&](std::size_t pb, std::size_t pe) {
        for (std::size_t t = pb; t < pe; ++t) widen_box_live(g, n * t / parts, n * (t + 1) / parts, part[t]);
      },
      parts, 1);
  bhcl_grid_dbox b = part[0];
  for (const bhcl_grid_dbox& p : part) unite_box(b, p);
  return b;
}

namespace {

// The live points' extreme coordinate along `axis` toward its high (or low) end: the planes of
// cells across the axis from that end inward, until one holds a live point (refit_box_faces). A
// plane's rows along x are one run of slots each where x is not the axis. No live point: the
// inverted box's value (+inf low, -inf high). False when the planes' cells would pass `budget`
// (cells left to look at, decremented).
bool live_extreme(const Grid& g, int axis, bool high, std::size_t& budget, float& out) {
  const bhcl_grid_geom& gm = g.geom;
  const std::uint32_t dim[3] = {gm.nx, gm.ny, gm.nz};
  const float* v = axis == 0 ? g.x.data() : axis == 1 ? g.y.data() : g.z.data();
  const std::int32_t* id = g.ids.data();
  const std::uint32_t* starts = g.starts.data();
  float best = high ? -INFINITY : INFINITY;
  auto take = [&](std::uint32_t c0, std::uint32_t c1) {  // the live slots of cells [c0, c1)
    const std::uint32_t a = bhcl_grid_start(starts, gm.sparse, c0), b = bhcl_grid_start(starts, gm.sparse, c1);
    for (std::uint32_t i = a; i < b; ++i)
      if (id[i] != BHCL_EMPTY_SLOT_ID) best = high ? std::max(best, v[i]) : std::min(best, v[i]);
  };
  const int u = axis == 2 ? 1 : 2;  // the outer axis of a plane's rows (z, or y for a z plane)
  const std::size_t plane_cells = std::size_t(gm.nx) * gm.ny * gm.nz / dim[axis];
  for (std::uint32_t s = 0; s < dim[axis]; ++s) {
    if (plane_cells > budget) return false;
    budget -= plane_cells;
    std::uint32_t c[3] = {0, 0, 0};
    c[axis] = high ? dim[axis] - 1u - s : s;
    for (c[u] = 0; c[u] < dim[u]; ++c[u]) {
      if (axis == 0) {  // cells one by one along y
        for (c[1] = 0; c[1] < dim[1]; ++c[1]) {
          const std::uint32_t cell = (c[2] * gm.ny + c[1]) * gm.nx + c[0];
          take(cell, cell + 1u);
        }
      } else {  // a row along x
        const std::uint32_t row = (c[2] * gm.ny + c[1]) * gm.nx;
        take(row, row + gm.nx);
      }
    }
    if (high ? best > -INFINITY : best < INFINITY) break;
  }
  out = best;
  return true;
}

}  // namespace

void refit_box_faces(Grid& g, unsigned faces, unsigned threads) {
  // At most a cell per four stored points looked at in all: past that (empty planes between a
  // removed outlier and the rest, a sparse directory's wide planes) every live point is read
  // instead, as before (the cells looked at then cost at most about a quarter more).
  std::size_t budget = std::max<std::size_t>(g.n_points / 4, 4096);
  float side[6] = {g.dbox.lx, g.dbox.hx, g.dbox.ly, g.dbox.hy, g.dbox.lz, g.dbox.hz};
  for (int f = 0; f < 6; ++f)
    if ((faces >> f & 1u) && !live_extreme(g, f >> 1, f & 1, budget, side[f])) {
      g.dbox = grid_points_box(g, threads);
      return;
    }
  g.dbox = bhcl_grid_dbox{side[0], side[2], side[4], side[1], side[3], side[5]};
}

void refresh_node_boxes(Grid& g, const std::vector<std::uint32_t>& cells) {
  const bhcl_grid_geom& gm = g.geom;
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(gm, &top_off, &total);
  if (top < 2 || g.occ.size() != bhcl_grid_occ_bytes(gm)) return;
  std::uint8_t* const boxes = g.occ.data() + bhcl_grid_tbox_off(total);
  std::vector<std::size_t> at(top + 1, 0);  // the first box of level l
  for (std::uint32_t l = 3; l <= top; ++l) at[l] = at[l - 1] + bhcl_grid_occ_size(gm, l - 1);
  auto box_at = [&](std::uint32_t l, std::size_t X, std::size_t Y, std::size_t Z) {
    return boxes + sizeof(bhcl_grid_dbox) *
                       bhcl_grid_occ_index(gm, std::uint32_t(at[l]), l, std::uint32_t(X), std::uint32_t(Y), std::uint32_t(Z));
  };
  const std::size_t nx = gm.nx, ny = gm.ny, nz = gm.nz, nxy = nx * ny;
  for (const std::uint32_t c : cells) {
    const std::size_t x = c % nx, y = (c / nx) % ny, z = c / nxy;
    bhcl_grid_dbox b = kEmptyBox;  // level 2: the points of its 4^3 cells
    for (std::size_t cz = z & ~std::size_t(3); cz < std::min(nz, (z | 3) + 1); ++cz)
      for (std::size_t cy = y & ~std::size_t(3); cy < std::min(ny, (y | 3) + 1); ++cy)
        for (std::size_t cx = x & ~std::size_t(3); cx < std::min(nx, (x | 3) + 1); ++cx) {
          const std::size_t cell = (cz * ny + cy) * nx + cx;
          widen_by_slots(b, g, g.start(cell), g.start(cell + 1));  // holes left out
        }
    std::memcpy(box_at(2, x >> 2, y >> 2, z >> 2), &b, sizeof(b));
    for (std::uint32_t l = 3; l <= top; ++l) {  // each ancestor: the union of its children
      const std::size_t X = x >> l, Y = y >> l, Z = z >> l;
      const std::size_t cx = bhcl_grid_occ_dim(gm.nx, l - 1), cy = bhcl_grid_occ_dim(gm.ny, l - 1);
      const std::size_t cz = bhcl_grid_occ_dim(gm.nz, l - 1);
      bhcl_grid_dbox u = kEmptyBox;
      for (unsigned o = 0; o < 8; ++o) {
        const std::size_t ux = 2 * X + (o & 1), uy = 2 * Y + ((o >> 1) & 1), uz = 2 * Z + (o >> 2);
        if (ux >= cx || uy >= cy || uz >= cz) continue;
        bhcl_grid_dbox child;
        std::memcpy(&child, box_at(l - 1, ux, uy, uz), sizeof(child));
        unite_box(u, child);
      }
      std::memcpy(box_at(l, X, Y, Z), &u, sizeof(u));
    }
  }
}

void build_grid_occupancy(Grid& g, unsigned threads) {
  const std::uint32_t top = start_pyramid(g);
  if (top < 2) {
    occupancy_level1(g, g.occ.data(), threads);
    return;
  }
  const Levels12 lv(g);
  detail::parallel_for(
      lv.dz,
      [&](std::size_t zb, std::size_t ze) {
        lv.empty_boxes(zb, ze);
        lv.from_cells(g, zb, ze);
        lv.bits2(zb, ze);
      },
      threads, 4);
  levels_above2(g, top, threads);
}

bool PyramidGather::apply(const bhcl_grid_geom& g) {
  std::uint32_t top_off = 0, total = 0;
  return !g.sparse && bhcl_grid_occ_top(g, &top_off, &total) >= 2;
}

void PyramidGather::start(Grid& g) {
  start_pyramid(g);
  owned.assign(bhcl_grid_occ_dim(g.geom.nz, 2), 0);
}

PyramidGather::Range PyramidGather::begin_range(Grid& g, std::size_t c_lo, std::size_t c_hi) {
  const std::size_t slab = std::size_t(4) * g.geom.nx * g.geom.ny;  // cells per level-2 z index
  const std::size_t zb = (c_lo + slab - 1) / slab;
  const std::size_t ze = c_hi == g.ncells() ? owned.size() : c_hi / slab;
  if (zb >= ze) return {0, 0};
  std::fill(owned.begin() + std::ptrdiff_t(zb), owned.begin() + std::ptrdiff_t(ze), std::uint8_t(1));
  Levels12(g).empty_boxes(zb, ze);
  return {zb * slab, std::min(g.ncells(), ze * slab)};
}

void PyramidGather::add_cells(Grid& g, const Range& r, std::size_t c0, std::size_t c1, std::uint32_t a,
                              const std::uint32_t* ends) const {
  const std::size_t lo = std::max(c0, r.c_lo), hi = std::min(c1, r.c_hi);  // the owned cells
  if (lo >= hi) return;
  if (lo > c0) a = ends[lo - 1 - c0];
  ends += lo - c0;
  const Levels12 lv(g);
  const std::size_t nx = g.geom.nx;
  for (std::size_t c = lo; c < hi;) {  // by pieces of rows
    const std::size_t row = c / nx, y = row % g.geom.ny, z = row / g.geom.ny, x0 = c - row * nx;
    const std::size_t x1 = std::min(nx, x0 + (hi - c));
    const std::uint32_t* const e = ends + (c - lo);  // e[x - x0]: the end of cell x of the row
    if (e[x1 - 1 - x0] != a) {  // the piece holds a point (the runs are adjacent)
      std::uint8_t* const bytes = lv.l1 + lv.row1(y, z);
      const std::size_t nodes = lv.row2(y, z);
      const unsigned yz = Levels12::row_bit1(y, z);
      for (std::size_t x = x0; x < x1;) {
        const std::size_t xb = std::min(x1, x + 16);
        if (e[xb - 1 - x0] == a) {  // 16 empty cells at once (the ends ascend)
          x = xb;
          continue;
        }
        while (x < xb) {  // by level-2 segments (4 cells, or the piece's part of one)
          const std::size_t xs = std::min(xb, (x | 3) + 1);
          const std::uint32_t b = e[xs - 1 - x0];
          if (b != a) {
            for (std::uint32_t prev = a; x < xs; ++x) {  // the segment's level-1 bits
              const std::uint32_t end = e[x - x0];
              if (end != prev) bytes[x >> 1] |= std::uint8_t(yz << (x & 1));
              prev = end;
            }
            bhcl_grid_dbox n = lv.box(nodes + ((xs - 1) >> 2));
            widen_by_slots_fresh(n, g, a, b);  // a fresh build stores no hole
            lv.set_box(nodes + ((xs - 1) >> 2), n);
            a = b;
          }
          x = xs;
        }
      }
    }
    c += x1 - x0;
  }
}

void PyramidGather::finish(Grid& g, unsigned threads) {
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(g.geom, &top_off, &total);
  const Levels12 lv(g);
  std::vector<std::size_t> rest;  // the slabs that no worker's range held whole
  for (std::size_t z = 0; z < owned.size(); ++z)
    if (!owned[z]) rest.push_back(z);
  detail::parallel_for(
      rest.size(),
      [&](std::size_t b, std::size_t e) {
        for (std::size_t i = b; i < e; ++i) {
          lv.empty_boxes(rest[i], rest[i] + 1);
          lv.from_cells(g, rest[i], rest[i] + 1);
        }
      },
      threads, 1);
  detail::parallel_for(
      lv.dz, [&](std::size_t zb, std::size_t ze) { lv.bits2(zb, ze); }, threads,
      std::max<std::size_t>(1, (std::size_t(1) << 16) / (lv.dx * lv.dy)));
  levels_above2(g, top, threads);
}

}  // namespace bhcl::blockhash
