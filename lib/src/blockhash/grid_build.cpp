// Block hashing, grid layout: the build by a parallel counting sort over the cells.
//   1. the box (parallel), 2. the cell side from a sample (the point-weighted mean population near
//   the target), 3. every point's cell (parallel), 4. the counts (relaxed atomics), the prefix,
//   5. a stable scatter into structure-of-arrays (parallel over disjoint cell ranges).
// No sort of the points: 15-35 ms for 1M points on 2 cores (../shared/limit/NOTES.md section 3).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>

#include "blockhash/grid.hpp"
#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"

namespace bhcl::blockhash {
namespace {

double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

struct Box {
  float lo[3] = {INFINITY, INFINITY, INFINITY};
  float hi[3] = {-INFINITY, -INFINITY, -INFINITY};
};

Box bounding_box(const float* xyz, std::size_t n, unsigned threads) {
  const unsigned t = threads ? threads : detail::default_threads();
  std::vector<Box> part(t);
  const std::size_t per = (n + t - 1) / t;
  detail::parallel_for(
      t,
      [&](std::size_t b, std::size_t e) {
        for (std::size_t c = b; c < e; ++c) {
          Box& x = part[c];
          for (std::size_t i = c * per; i < std::min(n, (c + 1) * per); ++i)
            for (int d = 0; d < 3; ++d) {
              x.lo[d] = std::min(x.lo[d], xyz[3 * i + d]);
              x.hi[d] = std::max(x.hi[d], xyz[3 * i + d]);
            }
        }
      },
      t, 1);
  Box out;
  for (const Box& x : part)
    for (int d = 0; d < 3; ++d) {
      out.lo[d] = std::min(out.lo[d], x.lo[d]);
      out.hi[d] = std::max(out.hi[d], x.hi[d]);
    }
  return out;
}

// The geometry for cell side h over the box (dims from the extents, margin from the magnitudes).
bhcl_grid_geom geometry(const Box& b, double h) {
  bhcl_grid_geom g{};
  g.ox = b.lo[0];
  g.oy = b.lo[1];
  g.oz = b.lo[2];
  g.h = static_cast<float>(h);
  g.inv_h = 1.0f / g.h;
  double mag = 0, ext = 0;
  std::uint32_t* dims[3] = {&g.nx, &g.ny, &g.nz};
  for (int d = 0; d < 3; ++d) {
    double e = double(b.hi[d]) - double(b.lo[d]);
    ext = std::max(ext, e);
    mag = std::max({mag, std::fabs(double(b.lo[d])), std::fabs(double(b.hi[d]))});
    double c = std::ceil(e / double(g.h));
    *dims[d] = static_cast<std::uint32_t>(std::clamp(c, 1.0, 2097152.0));
  }
  // The cell assignment (t - o) * inv_h and the slab edges o + i h each round by a few units in
  // the last place of the magnitudes involved: 2^-20 of them is a safe lower bound's slack.
  g.margin = static_cast<float>((mag + ext + double(g.h)) * std::ldexp(1.0, -20));
  return g;
}

// The point-weighted mean population of cells of side h, estimated from the sample (binomial
// thinning corrected: with fraction f, sum c^2 over sample cells = f^2 sum C^2 + f (1 - f) N).
double estimate_population(const std::vector<float>& s, std::size_t n, const Box& b, double h,
                           std::vector<std::uint64_t>& keys) {
  bhcl_grid_geom g = geometry(b, h);
  const std::size_t m = s.size() / 3;
  keys.resize(m);
  for (std::size_t i = 0; i < m; ++i) {
    std::uint64_t x = bhcl_grid_cell(s[3 * i], g.ox, g.inv_h, g.nx);
    std::uint64_t y = bhcl_grid_cell(s[3 * i + 1], g.oy, g.inv_h, g.ny);
    std::uint64_t z = bhcl_grid_cell(s[3 * i + 2], g.oz, g.inv_h, g.nz);
    keys[i] = (z * g.ny + y) * g.nx + x;
  }
  std::sort(keys.begin(), keys.end());
  double sum2 = 0;
  for (std::size_t i = 0; i < m;) {
    std::size_t j = i;
    while (j < m && keys[j] == keys[i]) ++j;
    sum2 += double(j - i) * double(j - i);
    i = j;
  }
  const double f = double(m) / double(n);
  return (sum2 - (1.0 - f) * double(m)) / (f * double(m));
}

double choose_cell_side(const float* xyz, std::size_t n, const Box& b, const GridBuildParams& p) {
  double ext = 0;
  for (int d = 0; d < 3; ++d) ext = std::max(ext, double(b.hi[d]) - double(b.lo[d]));
  if (!(ext > 0)) return 1.0;  // every point coincident: one cell
  const std::size_t stride = std::max<std::size_t>(1, n / std::max<std::size_t>(1, p.sample));
  std::vector<float> s;
  s.reserve(3 * (n / stride + 1));
  for (std::size_t i = 0; i < n; i += stride) s.insert(s.end(), xyz + 3 * i, xyz + 3 * i + 3);
  std::vector<std::uint64_t> keys;
  // Bisection on log h around the guess for points filling the box's volume (the population
  // falls as h shrinks): a bracket of 2^-12 .. 2^3 of it (surfaces and curves need smaller
  // cells than a volume), 14 steps (0.1 % in h).
  double vol = 1;
  int dims = 0;
  for (int d = 0; d < 3; ++d) {
    double e = double(b.hi[d]) - double(b.lo[d]);
    if (e > ext * 1e-6) vol *= e, ++dims;
  }
  const double guess = std::pow(vol * p.target_cell_points / double(n), 1.0 / std::max(1, dims));
  double lo = std::log(std::max(guess / 4096, ext * 1e-7)), hi = std::log(std::min(guess * 8, ext * 1.0001));
  if (!(lo < hi)) lo = hi - 1;
  if (estimate_population(s, n, b, std::exp(lo), keys) >= p.target_cell_points) return std::exp(lo);
  if (estimate_population(s, n, b, std::exp(hi), keys) < p.target_cell_points) return std::exp(hi);
  for (int it = 0; it < 14; ++it) {
    double mid = 0.5 * (lo + hi);
    if (estimate_population(s, n, b, std::exp(mid), keys) >= p.target_cell_points) hi = mid;
    else lo = mid;
  }
  return std::exp(hi);
}

}  // namespace

void build_grid(const float* xyz, std::size_t n, const GridBuildParams& p, Grid& g,
                GridBuildStats* stats) {
  if (n == 0 || n >= (std::size_t(1) << 31) - 1)
    throw Error("blockhash grid: the point count must be in [1, 2^31 - 2], got " + std::to_string(n));
  const unsigned threads = p.threads ? p.threads : detail::default_threads();
  GridBuildStats st;
  auto t0 = std::chrono::steady_clock::now();
  const Box box = bounding_box(xyz, n, threads);
  double h = p.cell_size > 0 ? p.cell_size : choose_cell_side(xyz, n, box, p);
  bhcl_grid_geom geom = geometry(box, h);
  // A direct table of at most max_cells_per_point cells per point (and 2^31): grow the cells.
  const double cap = std::min(std::max(p.max_cells_per_point * double(n), 65536.0), 2147483000.0);
  while (double(geom.nx) * geom.ny * geom.nz > cap) {
    h *= 1.05;
    geom = geometry(box, h);
    st.capped = true;
  }
  st.t_tune = since(t0);

  t0 = std::chrono::steady_clock::now();
  const std::size_t ncells = std::size_t(geom.nx) * geom.ny * geom.nz;
  std::vector<std::uint32_t> cell(n);
  detail::parallel_for(
      n,
      [&](std::size_t b, std::size_t e) {
        for (std::size_t i = b; i < e; ++i) {
          std::uint32_t cx = bhcl_grid_cell(xyz[3 * i], geom.ox, geom.inv_h, geom.nx);
          std::uint32_t cy = bhcl_grid_cell(xyz[3 * i + 1], geom.oy, geom.inv_h, geom.ny);
          std::uint32_t cz = bhcl_grid_cell(xyz[3 * i + 2], geom.oz, geom.inv_h, geom.nz);
          cell[i] = (cz * geom.ny + cy) * geom.nx + cx;
        }
      },
      threads, 65536);
  st.t_cells = since(t0);

  t0 = std::chrono::steady_clock::now();
  g.geom = geom;
  g.n_points = n;
  g.starts.assign(ncells + 1, 0);
  std::uint32_t* cnt = g.starts.data() + 1;
  detail::parallel_for(
      n,
      [&](std::size_t b, std::size_t e) {
        for (std::size_t i = b; i < e; ++i) __atomic_fetch_add(cnt + cell[i], 1u, __ATOMIC_RELAXED);
      },
      threads, 65536);
  double sum2 = 0;
  for (std::size_t c = 0; c < ncells; ++c) {
    std::uint32_t v = cnt[c];
    st.occupied += v ? 1 : 0;
    sum2 += double(v) * v;
    cnt[c] = g.starts[c] + v;  // starts[c + 1] = starts[c] + count(c)
  }
  st.mean_cell_points = sum2 / double(n);
  st.t_count = since(t0);

  t0 = std::chrono::steady_clock::now();
  g.x.resize(n + kGridPad);
  g.y.resize(n + kGridPad);
  g.z.resize(n + kGridPad);
  g.ids.resize(n + kGridPad);
  // Each thread owns a range of cells holding about n / t points and walks every point in order,
  // placing its own: stable (ties by caller index) whatever the thread count.
  const unsigned t = static_cast<unsigned>(std::min<std::size_t>(threads, std::max<std::size_t>(1, n / 65536)));
  std::vector<std::size_t> cut(t + 1, ncells);
  cut[0] = 0;
  for (unsigned j = 1; j < t; ++j)
    cut[j] = static_cast<std::size_t>(
        std::upper_bound(g.starts.begin(), g.starts.end(), std::uint32_t(n * j / t)) - g.starts.begin()) - 1;
  std::vector<std::uint32_t> pos(g.starts.begin(), g.starts.end() - 1);
  detail::parallel_for(
      t,
      [&](std::size_t b, std::size_t e) {
        for (std::size_t j = b; j < e; ++j) {
          const std::uint32_t c0 = std::uint32_t(cut[j]), c1 = std::uint32_t(cut[j + 1]);
          if (c0 >= c1) continue;
          for (std::size_t i = 0; i < n; ++i) {
            const std::uint32_t c = cell[i];
            if (c < c0 || c >= c1) continue;
            const std::uint32_t k = pos[c]++;
            g.x[k] = xyz[3 * i];
            g.y[k] = xyz[3 * i + 1];
            g.z[k] = xyz[3 * i + 2];
            g.ids[k] = static_cast<std::int32_t>(i);
          }
        }
      },
      t, 1);
  for (std::size_t i = n; i < n + kGridPad; ++i) {
    g.x[i] = g.y[i] = g.z[i] = INFINITY;
    g.ids[i] = -1;
  }
  st.t_scatter = since(t0);
  if (stats) *stats = st;
}

void Grid::validate(const std::string& what) const {
  auto bad = [&](const std::string& m) { throw Error(what + ": corrupt grid index: " + m); };
  if (geom.nx == 0 || geom.ny == 0 || geom.nz == 0) bad("a grid dimension is 0");
  if (!(geom.h > 0) || !std::isfinite(geom.h) || !(geom.inv_h > 0) || !std::isfinite(geom.inv_h))
    bad("the cell side is not a positive finite number");
  if (!std::isfinite(geom.ox) || !std::isfinite(geom.oy) || !std::isfinite(geom.oz) ||
      !(geom.margin >= 0) || !std::isfinite(geom.margin))
    bad("the origin or margin is not finite");
  if (double(geom.nx) * geom.ny * geom.nz > 2147483000.0) bad("too many cells");
  if (starts.size() != ncells() + 1) bad("the cell table has " + std::to_string(starts.size()) + " entries, not cells + 1");
  if (n_points == 0 || n_points >= (std::size_t(1) << 31) - 1) bad("the point count is out of range");
  if (starts.front() != 0 || starts.back() != n_points) bad("the cell table does not span the points");
  for (std::size_t c = 0; c + 1 < starts.size(); ++c)
    if (starts[c] > starts[c + 1]) bad("the cell table decreases at cell " + std::to_string(c));
  if (x.size() != n_points + kGridPad || y.size() != x.size() || z.size() != x.size() || ids.size() != x.size())
    bad("the point arrays have the wrong length");
  std::vector<bool> seen(n_points, false);
  for (std::size_t i = 0; i < n_points; ++i) {
    if (!std::isfinite(x[i]) || !std::isfinite(y[i]) || !std::isfinite(z[i]))
      bad("point " + std::to_string(i) + " is not finite");
    if (ids[i] < 0 || std::size_t(ids[i]) >= n_points || seen[std::size_t(ids[i])])
      bad("the ids are not a permutation (position " + std::to_string(i) + ")");
    seen[std::size_t(ids[i])] = true;
  }
  // Every point inside its cell: the search's slab bounds (and so its exactness) rely on it.
  for (std::size_t c = 0; c < ncells(); ++c)
    for (std::uint32_t i = starts[c]; i < starts[c + 1]; ++i) {
      std::size_t cx = bhcl_grid_cell(x[i], geom.ox, geom.inv_h, geom.nx);
      std::size_t cy = bhcl_grid_cell(y[i], geom.oy, geom.inv_h, geom.ny);
      std::size_t cz = bhcl_grid_cell(z[i], geom.oz, geom.inv_h, geom.nz);
      if ((cz * geom.ny + cy) * geom.nx + cx != c) bad("point " + std::to_string(i) + " lies outside its cell");
    }
}

}  // namespace bhcl::blockhash
