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

// Level 2's boxes from the points of their cells (holes, at +inf, left out): one task per level-2
// z index, which owns those boxes.
void boxes_level2(const Grid& g, bhcl_grid_dbox* box, unsigned threads) {
  const bhcl_grid_geom& gm = g.geom;
  const std::size_t ny = gm.ny, nz = gm.nz;
  const std::size_t dx = bhcl_grid_occ_dim(gm.nx, 2), dy = bhcl_grid_occ_dim(gm.ny, 2);
  detail::parallel_for(
      bhcl_grid_occ_dim(gm.nz, 2),
      [&](std::size_t zb, std::size_t ze) {
        std::fill(box + zb * dx * dy, box + ze * dx * dy, kEmptyBox);
        for (std::size_t z = 4 * zb; z < std::min(4 * ze, nz); ++z)
          for (std::size_t y = 0; y < ny; ++y) {
            bhcl_grid_dbox* const row = box + ((z >> 2) * dy + (y >> 2)) * dx;
            for_each_run(g, y, z, [&](std::size_t x, std::uint32_t a, std::uint32_t b) {
              // Widened in a local copy, the arrays through local pointers: widened in place, the
              // node's box could alias the points and was stored and reloaded at every point.
              bhcl_grid_dbox n = row[x >> 2];
              const float *const X = g.x.data(), *const Y = g.y.data(), *const Z = g.z.data();
              for (std::uint32_t i = a; i < b; ++i)
                if (X[i] < INFINITY) widen_box(n, X[i], Y[i], Z[i]);
              row[x >> 2] = n;
            });
          }
      },
      threads, 4);
}

// Each node of level l from its (up to 8) children of level l - 1: level[node] =
// make(child_at), where child_at(o) is the index in `below` of child o (bit 0: x, 1: y, 2: z)
// or -1 past the grid's edge. One task per level-l z index, which owns those nodes.
template <class T, class Make>
void from_children(const bhcl_grid_geom& gm, T* level, std::uint32_t l, unsigned threads, Make&& make) {
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
              level[(Z * dy + Y) * dx + X] = make(child_at);
            }
      },
      threads, 16);
}

// Level l >= 3's boxes: each the union of its children's.
void boxes_level(const bhcl_grid_geom& gm, const bhcl_grid_dbox* below, bhcl_grid_dbox* level, std::uint32_t l,
                 unsigned threads) {
  from_children(gm, level, l, threads, [&](auto child_at) {
    bhcl_grid_dbox b = kEmptyBox;
    for (unsigned o = 0; o < 8; ++o)
      if (const std::ptrdiff_t i = child_at(o); i >= 0) unite_box(b, below[i]);
    return b;
  });
}

// The boxes of levels 2..top (grid_search.h) into occ from byte `off` on.
void build_node_boxes(Grid& g, std::uint32_t top, std::size_t off, unsigned threads) {
  const bhcl_grid_geom& gm = g.geom;
  std::vector<bhcl_grid_dbox> box((g.occ.size() - off) / sizeof(bhcl_grid_dbox));
  boxes_level2(g, box.data(), threads);
  std::size_t at = 0;
  for (std::uint32_t l = 3; l <= top; ++l) {
    const std::size_t below = bhcl_grid_occ_size(gm, l - 1);
    boxes_level(gm, box.data() + at, box.data() + at + below, l, threads);
    at += below;
  }
  std::memcpy(g.occ.data() + off, box.data(), box.size() * sizeof(bhcl_grid_dbox));
}

// Level l >= 2 from level l - 1: a child's bit is set when its own byte is not 0.
void occupancy_level(const bhcl_grid_geom& gm, const std::uint8_t* below, std::uint8_t* level, std::uint32_t l,
                     unsigned threads) {
  from_children(gm, level, l, threads, [&](auto child_at) {
    unsigned m = 0;
    for (unsigned o = 0; o < 8; ++o)
      if (const std::ptrdiff_t i = child_at(o); i >= 0 && below[i]) m |= 1u << o;
    return std::uint8_t(m);
  });
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
          for (std::uint32_t i = g.start(cell), e = g.start(cell + 1); i < e; ++i)
            if (g.x[i] < INFINITY) widen_box(b, g.x[i], g.y[i], g.z[i]);
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
  const bhcl_grid_geom& gm = g.geom;
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(gm, &top_off, &total);
  g.occ.assign(bhcl_grid_occ_bytes(gm), std::uint8_t(0));  // the boxes' padding zeroed too
  std::uint8_t* const occ = g.occ.data();
  occupancy_level1(g, occ, threads);
  std::size_t off = 0;
  for (std::uint32_t l = 2; l <= top; ++l) {
    const std::size_t below = bhcl_grid_occ_size(gm, l - 1);
    occupancy_level(gm, occ + off, occ + off + below, l, threads);
    off += below;
  }
  if (top >= 2) build_node_boxes(g, top, bhcl_grid_tbox_off(total), threads);
}

}  // namespace bhcl::blockhash
