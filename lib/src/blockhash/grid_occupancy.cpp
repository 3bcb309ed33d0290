// Block hashing, grid layout: the occupancy pyramid (kernels/grid_search.h) from the directory.
// Built from the cells' runs rather than from the points, so it holds after inserts, removes and
// loads alike; a cell whose points were all removed stays marked until the compaction (its holes
// still fill its run), which costs a look, never a point.
#include <algorithm>

#include "blockhash/grid.hpp"
#include "core/parallel.hpp"

namespace bhcl::blockhash {
namespace {

// Level 1 from the fine cells, row by row: one task per level-1 z index, which owns those bytes.
void occupancy_level1(const Grid& g, std::uint8_t* occ, unsigned threads) {
  const bhcl_grid_geom& gm = g.geom;
  const std::size_t nx = gm.nx, ny = gm.ny, nz = gm.nz;
  const std::size_t dx = bhcl_grid_occ_dim(gm.nx, 1), dy = bhcl_grid_occ_dim(gm.ny, 1);
  const std::uint32_t* const st = g.starts.data();
  const bool sparse = gm.sparse != 0;
  constexpr std::size_t kSeg = std::size_t(1) << BHCL_GRID_SEG_BITS;
  detail::parallel_for(
      bhcl_grid_occ_dim(gm.nz, 1),
      [&](std::size_t zb, std::size_t ze) {
        std::fill(occ + zb * dx * dy, occ + ze * dx * dy, std::uint8_t(0));
        for (std::size_t z = 2 * zb; z < std::min(2 * ze, nz); ++z)
          for (std::size_t y = 0; y < ny; ++y) {
            std::uint8_t* const row = occ + ((z >> 1) * dy + (y >> 1)) * dx;
            const unsigned yz = unsigned(((y & 1) << 1) | ((z & 1) << 2));
            std::size_t c = (z * ny + y) * nx;
            if (!sparse) {
              for (std::size_t x = 0; x < nx; ++x, ++c)
                if (st[c + 1] > st[c]) row[x >> 1] |= std::uint8_t(1u << ((x & 1) | yz));
              continue;
            }
            std::uint32_t a = g.start(c);
            for (std::size_t x = 0; x < nx;) {
              // A two-level directory's empty segment: 16 empty cells at once.
              if ((c & (kSeg - 1)) == 0 && x + kSeg <= nx && (st[c >> BHCL_GRID_SEG_BITS] & BHCL_GRID_EMPTY_SEG)) {
                x += kSeg, c += kSeg;
                a = g.start(c);
                continue;
              }
              const std::uint32_t b = g.start(c + 1);
              if (b > a) row[x >> 1] |= std::uint8_t(1u << ((x & 1) | yz));
              a = b;
              ++x, ++c;
            }
          }
      },
      threads, 8);
}

// Level l >= 2 from level l - 1: a child's bit is set when its own byte is not 0.
void occupancy_level(const bhcl_grid_geom& gm, const std::uint8_t* below, std::uint8_t* level, std::uint32_t l,
                     unsigned threads) {
  const std::size_t cx = bhcl_grid_occ_dim(gm.nx, l - 1), cy = bhcl_grid_occ_dim(gm.ny, l - 1);
  const std::size_t cz = bhcl_grid_occ_dim(gm.nz, l - 1);
  const std::size_t dx = bhcl_grid_occ_dim(gm.nx, l), dy = bhcl_grid_occ_dim(gm.ny, l);
  detail::parallel_for(
      bhcl_grid_occ_dim(gm.nz, l),
      [&](std::size_t zb, std::size_t ze) {
        for (std::size_t Z = zb; Z < ze; ++Z)
          for (std::size_t Y = 0; Y < dy; ++Y)
            for (std::size_t X = 0; X < dx; ++X) {
              unsigned m = 0;
              for (unsigned o = 0; o < 8; ++o) {
                const std::size_t x = 2 * X + (o & 1), y = 2 * Y + ((o >> 1) & 1), z = 2 * Z + (o >> 2);
                if (x < cx && y < cy && z < cz && below[(z * cy + y) * cx + x]) m |= 1u << o;
              }
              level[(Z * dy + Y) * dx + X] = std::uint8_t(m);
            }
      },
      threads, 16);
}

}  // namespace

std::size_t grid_occupancy_bytes(const bhcl_grid_geom& g) {
  std::uint32_t top_off = 0, total = 0;
  bhcl_grid_occ_top(g, &top_off, &total);
  return total;
}

// The box of the live points (holes, at +inf, left out).
bhcl_grid_dbox grid_points_box(const Grid& g, unsigned threads) {
  const std::size_t n = g.n_points;
  if (n == 0) return bhcl_grid_dbox{-INFINITY, -INFINITY, -INFINITY, INFINITY, INFINITY, INFINITY};
  const unsigned parts = std::max(1u, std::min(threads ? threads : detail::default_threads(), 64u));
  std::vector<bhcl_grid_dbox> part(parts, bhcl_grid_dbox{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY});
  detail::parallel_for(
      parts,
      [&](std::size_t pb, std::size_t pe) {
        for (std::size_t t = pb; t < pe; ++t) {
          bhcl_grid_dbox b = part[t];
          for (std::size_t i = n * t / parts, e = n * (t + 1) / parts; i < e; ++i) {
            if (g.x[i] < INFINITY) widen_box(b, g.x[i], g.y[i], g.z[i]);  // not a hole (+inf)
          }
          part[t] = b;
        }
      },
      parts, 1);
  bhcl_grid_dbox b = part[0];
  for (const bhcl_grid_dbox& p : part) {
    b.lx = std::min(b.lx, p.lx), b.ly = std::min(b.ly, p.ly), b.lz = std::min(b.lz, p.lz);
    b.hx = std::max(b.hx, p.hx), b.hy = std::max(b.hy, p.hy), b.hz = std::max(b.hz, p.hz);
  }
  return b;
}

void build_grid_occupancy(Grid& g, unsigned threads) {
  const bhcl_grid_geom& gm = g.geom;
  std::uint32_t top_off = 0, total = 0;
  const std::uint32_t top = bhcl_grid_occ_top(gm, &top_off, &total);
  g.occ.resize(total);
  std::uint8_t* const occ = g.occ.data();
  occupancy_level1(g, occ, threads);
  std::size_t off = 0;
  for (std::uint32_t l = 2; l <= top; ++l) {
    const std::size_t below = bhcl_grid_occ_size(gm, l - 1);
    occupancy_level(gm, occ + off, occ + off + below, l, threads);
    off += below;
  }
}

}  // namespace bhcl::blockhash
