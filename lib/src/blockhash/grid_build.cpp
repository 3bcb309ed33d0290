// Block hashing, grid layout: the build by a parallel counting sort over the cells.
//   1. the box (parallel), 2. the cell side from a sample (the point-weighted mean population near
//   the target), 3. every point's cell (parallel), 4. the counts (relaxed atomics), the prefix,
//   5. a stable scatter into structure-of-arrays (parallel over disjoint cell ranges).
// No sort of the points: 15-35 ms for 1M points on 2 cores (docs/PERFORMANCE.md, the build).
#include <sys/mman.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <cmath>
#include <limits>

#include "blockhash/grid.hpp"
#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"
#include "core/point_scan.hpp"

#ifndef BHCL_GRID_BUCKETS
#define BHCL_GRID_BUCKETS 256
#endif

namespace bhcl::blockhash {
namespace {

double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// v sized n, its old contents not kept: a vector growing past its capacity is freed first, so
// that the build neither copies the previous build's arrays into the new ones (a 25 % insert's
// rebuild copied 16 MB of records it then overwrote) nor holds both at once.
// room: the capacity an allocation reserves past n, in eighths of n (the point arrays keep an
// eighth so that an insert merges in place, grid_update.cpp; capacity never written is never
// faulted in, so it costs address space only; half again, tried so that a rebuild after a 25 %
// insert could write into the old arrays, made fresh builds about 12 % slower in update_bench).
template <typename T>
void resize_discarding(GridVec<T>& v, std::size_t n, std::size_t room_eighths = 0) {
  if (v.capacity() < n) {
    GridVec<T>().swap(v);
    v.reserve(n + n / 8 * room_eighths);
#ifdef MADV_NOHUGEPAGE
    // The room in small pages: an insert that first writes there faults in a few 4 KiB pages,
    // where a huge page's fault could compact memory first (THP defrag "madvise": 8-17 ms of CPU
    // in a 10 % insert's merge under memory pressure, against 3-4 ms).
    constexpr std::uintptr_t kHuge = std::uintptr_t(2) << 20;
    const std::uintptr_t from = (reinterpret_cast<std::uintptr_t>(v.data() + n) + kHuge - 1) & ~(kHuge - 1);
    const std::uintptr_t to = reinterpret_cast<std::uintptr_t>(v.data() + v.capacity()) & ~(std::uintptr_t(4095));
    if (room_eighths && to > from) ::madvise(reinterpret_cast<void*>(from), to - from, MADV_NOHUGEPAGE);
#endif
  }
  v.resize(n);
}

struct Box {
  float lo[3] = {INFINITY, INFINITY, INFINITY};
  float hi[3] = {-INFINITY, -INFINITY, -INFINITY};
};

// The AoS part scanned, the SoA part's box as given.
Box bounding_box(const GridInput& in, unsigned threads) {
  Box out;
  if (in.n_aos) {
    const detail::PointScan ps = detail::scan_points(in.xyz, in.n_aos, threads);
    for (int d = 0; d < 3; ++d) out.lo[d] = ps.lo[d], out.hi[d] = ps.hi[d];
  }
  if (in.n_soa)
    for (int d = 0; d < 3; ++d) out.lo[d] = std::min(out.lo[d], in.soa_lo[d]), out.hi[d] = std::max(out.hi[d], in.soa_hi[d]);
  return out;
}

// Point i of the input (the SoA part first).
void input_point(const GridInput& in, std::size_t i, float* p) {
  if (i < in.n_soa) {
    p[0] = in.x[i], p[1] = in.y[i], p[2] = in.z[i];
    return;
  }
  const float* q = in.xyz + 3 * (i - in.n_soa);
  p[0] = q[0], p[1] = q[1], p[2] = q[2];
}

// The tuning's sample: every n / sample-th point, or for an input with a SoA part points at
// random positions (a fixed seed: the same input gives the same side).
std::vector<float> tuning_sample(const GridInput& in, std::size_t sample) {
  const std::size_t n = in.size();
  const std::size_t stride = std::max<std::size_t>(1, n / std::max<std::size_t>(1, sample));
  std::vector<float> s(3 * ((n + stride - 1) / stride));
  std::uint64_t state = 0x9E3779B97F4A7C15ull ^ n;
  for (std::size_t i = 0, k = 0; i < n; i += stride, ++k) {
    std::size_t at = i;
    if (in.n_soa) {  // splitmix64
      std::uint64_t z = (state += 0x9E3779B97F4A7C15ull);
      z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
      z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
      at = static_cast<std::size_t>((z ^ (z >> 31)) % n);
    }
    input_point(in, at, s.data() + 3 * k);
  }
  return s;
}

// The geometry for cell side h over the box (dims from the extents, margin from the magnitudes).
// `slack`: one cell more along every axis the points extend over, the box centred in it, so that
// at least half a cell lies beyond the points on each side: an insert of points from the same
// distribution (a new point a little past the old extremes) then merges into the cells instead
// of forcing a full build (grid_update.cpp). The tuning's estimates use the plain box.
bhcl_grid_geom geometry(const Box& b, double h, bool slack = false) {
  bhcl_grid_geom g{};
  g.h = static_cast<float>(h);
  g.inv_h = 1.0f / g.h;
  double mag = 0, ext = 0;
  for (int d = 0; d < 3; ++d) ext = std::max(ext, double(b.hi[d]) - double(b.lo[d]));
  std::uint32_t* dims[3] = {&g.nx, &g.ny, &g.nz};
  float* origin[3] = {&g.ox, &g.oy, &g.oz};
  for (int d = 0; d < 3; ++d) {
    double e = double(b.hi[d]) - double(b.lo[d]);
    double c = std::ceil(e / double(g.h));
    double o = b.lo[d];
    if (slack && e > ext * 1e-6 && c + 1 <= 2097152.0) {
      c += 1;
      o = double(b.lo[d]) - (c * double(g.h) - e) / 2;
    }
    *origin[d] = std::min(static_cast<float>(o), b.lo[d]);  // never above the lowest point
    *dims[d] = static_cast<std::uint32_t>(std::clamp(c, 1.0, 2097152.0));
    mag = std::max({mag, std::fabs(double(*origin[d])), std::fabs(double(b.hi[d])),
                    std::fabs(double(*origin[d]) + double(*dims[d]) * h)});
  }
  if (slack) ext += 2 * h;
  // The cell assignment (t - o) * inv_h and the slab edges o + i h each round by a few units in
  // the last place of the magnitudes involved: 2^-20 of them is a safe lower bound's slack.
  g.margin = static_cast<float>((mag + ext + double(g.h)) * std::ldexp(1.0, -20));
  return g;
}

// The point-weighted mean population of cells of side h, estimated from the sample (binomial
// thinning corrected: with fraction f, sum c^2 over sample cells = f^2 sum C^2 + f (1 - f) N).
// The sample's cells are counted in an open-addressing table (2x the sample, keys + 1, 0 empty):
// the sort of the keys it replaces was most of a fresh build's tuning (4 of 5 ms on Cornell 1M).
// The sum of squared counts is an integer either way, so the side chosen is the same.
double estimate_population(const std::vector<float>& s, std::size_t n, const Box& b, double h,
                           std::vector<std::uint64_t>& table, std::vector<std::uint32_t>& count) {
  bhcl_grid_geom g = geometry(b, h);
  const std::size_t m = s.size() / 3;
  unsigned bits = 4;
  while ((std::size_t(1) << bits) < 2 * m) ++bits;
  const std::size_t size = std::size_t(1) << bits, mask = size - 1;
  table.assign(size, 0);
  count.resize(size);
  std::uint64_t sum2 = 0;
  for (std::size_t i = 0; i < m; ++i) {
    const std::uint64_t x = bhcl_grid_cell(s[3 * i], g.ox, g.inv_h, g.nx);
    const std::uint64_t y = bhcl_grid_cell(s[3 * i + 1], g.oy, g.inv_h, g.ny);
    const std::uint64_t z = bhcl_grid_cell(s[3 * i + 2], g.oz, g.inv_h, g.nz);
    const std::uint64_t key = (z * g.ny + y) * g.nx + x + 1;
    std::size_t at = static_cast<std::size_t>((key * 0x9E3779B97F4A7C15ull) >> (64 - bits));
    while (table[at] != 0 && table[at] != key) at = (at + 1) & mask;
    if (table[at] == 0) {
      table[at] = key;
      count[at] = 0;
    }
    sum2 += 2 * std::uint64_t(count[at]) + 1;  // (c + 1)^2 - c^2
    ++count[at];
  }
  const double f = double(m) / double(n);
  return (double(sum2) - (1.0 - f) * double(m)) / (f * double(m));
}

// The cell side whose point-weighted mean population is the target, within 4 %: a safeguarded
// secant search on log h (the population grows with h, about as h^d for points on a d-dimensional
// set), each step one count of the sample's cells. 3-6 steps where a bisection took 16.
double choose_cell_side(const GridInput& in, const Box& b, const GridBuildArgs& p) {
  const std::size_t n = in.size();
  double ext = 0;
  for (int d = 0; d < 3; ++d) ext = std::max(ext, double(b.hi[d]) - double(b.lo[d]));
  if (!(ext > 0)) return 1.0;  // every point coincident: one cell
  const std::vector<float> s = tuning_sample(in, p.sample);
  std::vector<std::uint64_t> table;
  std::vector<std::uint32_t> count;
  double vol = 1;
  int dims = 0;
  for (int d = 0; d < 3; ++d) {
    double e = double(b.hi[d]) - double(b.lo[d]);
    if (e > ext * 1e-6) vol *= e, ++dims;
  }
  // The guess for points filling the box's volume; surfaces and curves need larger cells than it,
  // clusters smaller: the search stays within 2^-12 .. 2^3 of it (and inside the box).
  const double guess = std::pow(vol * p.target_cell_points / double(n), 1.0 / std::max(1, dims));
  const double xlo = std::log(std::max(guess / 4096, ext * 1e-7));
  const double xhi = std::log(std::min(guess * 8, ext * 1.0001));
  if (!(xlo < xhi)) return std::exp(xhi);
  const double target = std::log(p.target_cell_points), tol = std::log(1.04);
  // f(x) = log population(e^x) - log target, increasing in x.
  auto f = [&](double x) {
    return std::log(std::max(estimate_population(s, n, b, std::exp(x), table, count), 1e-9)) - target;
  };
  double x0 = std::clamp(std::log(guess), xlo, xhi), f0 = f(x0);
  if (std::fabs(f0) < tol) return std::exp(x0);
  // Bracket: steps of the secant's size from the guess (at least one doubling), toward the target.
  double a = x0, fa = f0, bx = x0, fb = f0, slope = double(std::max(1, dims));
  for (int it = 0; it < 12 && (fa < 0) == (fb < 0); ++it) {
    a = bx, fa = fb;
    double step = std::clamp(-fa / slope, -4.0 * std::log(2.0), 4.0 * std::log(2.0));
    if (std::fabs(step) < std::log(2.0) * 0.25) step = fa < 0 ? std::log(2.0) * 0.25 : -std::log(2.0) * 0.25;
    bx = std::clamp(a + step, xlo, xhi);
    if (bx == a) return std::exp(a);  // at an end of the range: the best this search allows
    fb = f(bx);
    if (std::fabs(fb) < tol) return std::exp(bx);
    if (fb != fa) slope = std::max(0.25, (fb - fa) / (bx - a));
  }
  if ((fa < 0) == (fb < 0)) return std::exp(std::fabs(fa) < std::fabs(fb) ? a : bx);
  // Illinois regula falsi inside the bracket.
  int side = 0;
  for (int it = 0; it < 8; ++it) {
    if (!(fb != fa)) break;
    const double x = (a * fb - bx * fa) / (fb - fa), fx = f(x);
    if (std::fabs(fx) < tol) return std::exp(x);
    if ((fx < 0) == (fb < 0)) {
      bx = x, fb = fx;
      if (side == -1) fa *= 0.5;
      side = -1;
    } else {
      a = x, fa = fx;
      if (side == 1) fb *= 0.5;
      side = 1;
    }
  }
  return std::exp(std::fabs(fa) < std::fabs(fb) ? a : bx);
}

// The buckets of the first pass: few enough that a thread's write streams (two per bucket) stay
// in L1 and its TLB, many enough that a bucket's counts and records stay in L2.
constexpr std::size_t kBuckets = BHCL_GRID_BUCKETS;

// Per-thread scratch of the bucket pass (each cell range of a bucket counted locally); zero
// between buckets: every entry a bucket touches is cleared before the next.
struct BucketScratch {
  std::vector<std::uint32_t> cnt;
  std::vector<std::uint8_t> seg;
  std::vector<std::uint32_t> rank;
  std::vector<std::uint32_t> lcell;  // each record's cell in the bucket's counts, computed once
};

std::size_t cell_count(const bhcl_grid_geom& g) { return std::size_t(g.nx) * g.ny * g.nz; }

// The cells a build uses: side h (the caller's or from a sample), grown by 5 % steps until the
// directory fits. A direct table of at most max_cells_per_point cells per point; past it a
// two-level directory of up to 16x as many cells (its top level then holds as many entries as
// the direct table would); past that (and 2^31 cells) the cells grow until the table fits.
bhcl_grid_geom grid_shape(const GridInput& in, const Box& box, const GridBuildArgs& p, GridBuildStats& st) {
  const std::size_t n = in.size();
  double h = p.cell_size > 0 ? p.cell_size : choose_cell_side(in, box, p);
  if (!(h > 0) || !std::isfinite(h))
    throw Error("blockhash grid: the cell side came out as " + std::to_string(h) + " (internal error)");
  bhcl_grid_geom geom = geometry(box, h, true);
  const double direct_cap = std::min(std::max(p.max_cells_per_point * double(n), 65536.0), 2147483000.0);
  auto cells_of = [](const bhcl_grid_geom& gg) { return double(gg.nx) * gg.ny * gg.nz; };
  bool sparse = p.directory == 1 || (p.directory == -1 && cells_of(geom) > direct_cap);
  const double cap = sparse ? std::min(direct_cap * double(1u << BHCL_GRID_SEG_BITS), 2147483000.0) : direct_cap;
  while (cells_of(geom) > cap) {
    h *= 1.05;
    geom = geometry(box, h, true);
    st.capped = true;
  }
  if (p.directory == -1 && sparse && cells_of(geom) <= direct_cap) sparse = false;
  geom.sparse = sparse ? BHCL_GRID_SEG_BITS : 0u;
  return geom;
}

// Buckets: ranges of 2^shift cells (whole segments), at most kBuckets of them, so that a bucket's
// counts and records stay in cache while its cells are sorted. start[b] .. start[b + 1]: bucket
// b's records in the scratch's rec.
struct Buckets {
  std::size_t ncells = 0, nb = 0;
  unsigned shift = 0;
  std::vector<std::uint32_t> start;
};

// A 16-byte record (x, y, z, id as a float's bits) written and read back. The id goes through
// a local float and a plain store: a memcpy store into the record may alias anything, and made
// the compiler reload every pointer on every record (35 % of a rebuild's time in pass 2).
inline void put_record(float* r, float x, float y, float z, std::int32_t id) {
  float idf;
  std::memcpy(&idf, &id, 4);
  r[0] = x;
  r[1] = y;
  r[2] = z;
  r[3] = idf;
}

// Record r into slot k of the point arrays.
inline void take_record(const float* r, float* X, float* Y, float* Z, std::int32_t* I, std::size_t k) {
  std::int32_t id;
  std::memcpy(&id, r + 3, 4);
  X[k] = r[0];
  Y[k] = r[1];
  Z[k] = r[2];
  I[k] = id;
}

// A record's cell, as pass 1 computed it (the same function of the same coordinates).
struct RecordCell {
  const float* rec;
  bhcl_grid_geom g;
  std::uint32_t operator()(std::uint32_t r) const {
    const float* p = rec + 4 * std::size_t(r);
    return grid_cell_index(g, p[0], p[1], p[2]);
  }
};

// f(i, x, y, z, id) for the input's points i in [b, e): one tight loop per part.
template <typename F>
void for_input(const GridInput& in, std::size_t b, std::size_t e, F&& f) {
  const float *const X = in.x, *const Y = in.y, *const Z = in.z;
  const std::int32_t* const SI = in.soa_ids;
  for (std::size_t i = b, se = std::min(e, in.n_soa); i < se; ++i) f(i, X[i], Y[i], Z[i], SI[i]);
  const float* const P = in.xyz;
  const std::int32_t* const AI = in.aos_ids;
  const std::int64_t id0 = in.aos_first >= 0 ? in.aos_first - std::int64_t(in.n_soa) : 0;  // id = i + id0
  for (std::size_t i = std::max(b, in.n_soa); i < e; ++i) {
    const std::size_t j = i - in.n_soa;
    f(i, P[3 * j], P[3 * j + 1], P[3 * j + 2], AI ? AI[j] : static_cast<std::int32_t>(std::int64_t(i) + id0));
  }
}

// Passes 1 and 2: every point's cell and, per thread, the points of each bucket; then each
// bucket's records, thread by thread in input order (so the sort is stable whatever the thread
// count): 16-byte (x, y, z, id) records, written in one pass.
Buckets bucket_records(const GridInput& in, const bhcl_grid_geom& geom, unsigned threads, GridScratch& sc,
                       GridBuildStats& st) {
  auto t0 = std::chrono::steady_clock::now();
  const std::size_t n = in.size();
  Buckets bk;
  bk.ncells = cell_count(geom);
  bk.shift = geom.sparse ? BHCL_GRID_SEG_BITS : 0;
  while ((bk.ncells >> bk.shift) > kBuckets) ++bk.shift;
  const unsigned shift = bk.shift;
  const std::size_t nb = bk.nb = ((bk.ncells - 1) >> shift) + 1;
  const unsigned T = static_cast<unsigned>(std::min<std::size_t>(threads, std::max<std::size_t>(1, n / 65536)));
  const std::size_t per = (n + T - 1) / T;
  resize_discarding(sc.cell, n, 2);  // a quarter of room: a rebuild after a large insert reuses it
  std::vector<std::uint32_t> hist(std::size_t(T) * nb, 0);
  detail::parallel_for(
      T,
      [&](std::size_t tb, std::size_t te) {
        // The geometry and the arrays in locals: the stores below (to uint32_t) would otherwise
        // make the compiler reload them through `geom` and the vectors on every point.
        const bhcl_grid_geom gg = geom;
        std::uint32_t* const cell = sc.cell.data();
        for (std::size_t j = tb; j < te; ++j) {
          std::uint32_t* const hj = hist.data() + j * nb;
          for_input(in, j * per, std::min(n, (j + 1) * per), [&](std::size_t i, float x, float y, float z, std::int32_t) {
            const std::uint32_t c = grid_cell_index(gg, x, y, z);
            cell[i] = c;
            ++hj[c >> shift];
          });
        }
      },
      T, 1);
  st.t_cells = since(t0);

  t0 = std::chrono::steady_clock::now();
  std::vector<std::uint32_t>& bstart = bk.start;
  bstart.assign(nb + 1, 0);
  for (std::size_t b = 0; b < nb; ++b) {
    std::uint32_t s = bstart[b];
    for (unsigned j = 0; j < T; ++j) {
      const std::uint32_t v = hist[j * nb + b];
      hist[j * nb + b] = s;
      s += v;
    }
    bstart[b + 1] = s;
  }
  resize_discarding(sc.rec, 4 * n, 2);
  detail::parallel_for(
      T,
      [&](std::size_t tb, std::size_t te) {
        // Pointers in locals (put_record says why). The record's cell is not stored beside it:
        // pass 3 computes it again from the record (in cache there), where a second scattered
        // store stream was 70 % of this loop's samples.
        const std::uint32_t* const cell = sc.cell.data();
        float* const rec = sc.rec.data();
        for (std::size_t j = tb; j < te; ++j) {
          std::uint32_t* const pos = hist.data() + j * nb;
          for_input(in, j * per, std::min(n, (j + 1) * per), [&](std::size_t i, float x, float y, float z, std::int32_t id) {
            put_record(rec + 4 * std::size_t(pos[cell[i] >> shift]++), x, y, z, id);
          });
        }
      },
      T, 1);
  st.t_count = since(t0);

  return bk;
}

// The two-level directory: the occupied segments before each bucket (seg_base[b]; seg_base[nb]:
// all of them), so that each bucket knows where its segment tables go.
std::vector<std::uint32_t> number_segments(const Buckets& bk, const RecordCell& rec_cell, unsigned threads) {
  const std::size_t nb = bk.nb;
  const std::size_t seg_per_bucket = std::size_t(1) << (bk.shift - BHCL_GRID_SEG_BITS);
  std::vector<std::uint32_t> seg_base(nb + 1, 0);
  const std::vector<std::uint32_t>& bstart = bk.start;
  const unsigned shift = bk.shift;
  detail::parallel_chunks(nb, 1, threads, [&](std::size_t b, std::size_t, std::size_t) {
    static thread_local BucketScratch ws;
    if (ws.seg.size() < seg_per_bucket) ws.seg.assign(seg_per_bucket, 0);
    const std::size_t s0 = (b << shift) >> BHCL_GRID_SEG_BITS;
    std::uint32_t occ = 0;
    for (std::uint32_t r = bstart[b]; r < bstart[b + 1]; ++r) {
      std::uint8_t& m = ws.seg[(rec_cell(r) >> BHCL_GRID_SEG_BITS) - s0];
      occ += m ? 0 : 1;
      m = 1;
    }
    for (std::uint32_t r = bstart[b]; r < bstart[b + 1]; ++r) ws.seg[(rec_cell(r) >> BHCL_GRID_SEG_BITS) - s0] = 0;
    seg_base[b + 1] = occ;
  });
  for (std::size_t b = 0; b < nb; ++b) seg_base[b + 1] += seg_base[b];
  return seg_base;
}

// What pass 3 found in one bucket: its occupied cells and the sum of its cells' squared counts.
struct BucketCounts {
  std::uint32_t occupied = 0;
  std::uint64_t sum2 = 0;
};

// Direct table: the bucket's cells counted, and their starts written. The write position of cell
// c is kept at starts[c + 1]: after the placement it has moved to the cell's end, which is where
// cell c + 1 starts. No second table of positions, and the counts are cleared as they are read.
// Buckets write disjoint entries (c0, c1].
BucketCounts count_direct(std::size_t c0, std::size_t c1, std::uint32_t rb, std::uint32_t re,
                          const RecordCell& rec_cell, BucketScratch& ws, Grid& g) {
  BucketCounts bc;
  std::uint32_t* const cnt = ws.cnt.data();
  std::uint32_t* const lcell = ws.lcell.data();
  std::uint32_t run = rb;
  const std::uint32_t cb = static_cast<std::uint32_t>(c0);
  for (std::uint32_t r = rb; r < re; ++r) {
    const std::uint32_t lc = rec_cell(r) - cb;
    lcell[r - rb] = lc;
    ++cnt[lc];
  }
  std::uint32_t* const next = g.starts.data() + c0 + 1;
  std::uint32_t occ = 0;
  std::uint64_t sum2 = 0;  // in integers: a double's add chain was the prefix loop's bound
  for (std::size_t i = 0, m = c1 - c0; i < m; ++i) {
    const std::uint32_t v = cnt[i];
    cnt[i] = 0;
    next[i] = run;
    run += v;
    occ += v ? 1 : 0;
    sum2 += std::uint64_t(v) * v;
  }
  bc.occupied = occ;
  bc.sum2 = sum2;
  return bc;
}

// Two-level: the bucket's occupied segments ranked in order, and each cell counted at (rank,
// cell in segment): the counts of a sparse bucket stay a few KiB, not a count per cell of its
// range (1.5 MiB per bucket for the Cornell box at 10M points). The counts become the cells'
// write positions; *nocc gets the bucket's occupied segments.
BucketCounts count_two_level(std::size_t c0, std::size_t c1, std::uint32_t rb, std::uint32_t re,
                             std::uint32_t seg_base, std::size_t top, const RecordCell& rec_cell,
                             BucketScratch& ws, Grid& g, std::uint32_t* nocc_out) {
  constexpr std::uint32_t kSeg = 1u << BHCL_GRID_SEG_BITS;
  std::uint32_t* const cnt = ws.cnt.data();
  std::uint32_t* const lcell = ws.lcell.data();
  const std::size_t s0 = c0 >> BHCL_GRID_SEG_BITS;
  const std::size_t s1 = std::min(((c1 - 1) >> BHCL_GRID_SEG_BITS) + 1, top);
  std::uint32_t nocc = 0, occ = 0, run = rb;
  std::uint64_t sum2 = 0;
  const std::uint32_t cb = static_cast<std::uint32_t>(c0);
  for (std::uint32_t r = rb; r < re; ++r) {
    const std::uint32_t rel = rec_cell(r) - cb;
    lcell[r - rb] = rel;
    ws.seg[rel >> BHCL_GRID_SEG_BITS] = 1;
  }
  for (std::size_t sg = s0; sg < s1; ++sg)
    if (ws.seg[sg - s0]) ws.rank[sg - s0] = nocc++;
  // c0 is a whole number of segments: a cell's place in its segment is rel's low bits.
  for (std::uint32_t r = rb; r < re; ++r) {
    const std::uint32_t rel = lcell[r - rb];
    const std::uint32_t lc = (ws.rank[rel >> BHCL_GRID_SEG_BITS] << BHCL_GRID_SEG_BITS) | (rel & (kSeg - 1u));
    lcell[r - rb] = lc;
    ++cnt[lc];
  }
  const std::uint32_t slot0 = static_cast<std::uint32_t>(top) + (seg_base << BHCL_GRID_SEG_BITS);
  for (std::size_t sg = s0; sg < s1; ++sg) {
    if (!ws.seg[sg - s0]) {
      g.starts[sg] = BHCL_GRID_EMPTY_SEG | run;
      continue;
    }
    ws.seg[sg - s0] = 0;
    const std::uint32_t rk = ws.rank[sg - s0], slot = slot0 + (rk << BHCL_GRID_SEG_BITS);
    g.starts[sg] = slot;
    for (std::uint32_t j = 0; j < kSeg; ++j) {
      const std::uint32_t lc = (rk << BHCL_GRID_SEG_BITS) | j;
      const std::uint32_t v = cnt[lc];
      g.starts[slot + j] = run;
      cnt[lc] = run;  // now the cell's write position
      run += v;
      occ += v ? 1 : 0;
      sum2 += std::uint64_t(v) * v;
    }
  }
  *nocc_out = nocc;
  return {occ, sum2};
}

// The bucket's records placed at their cells' write positions (pos[local cell]++), stable.
void place_records(std::uint32_t rb, std::uint32_t re, const std::uint32_t* lcell, std::uint32_t* pos,
                   const float* rec, Grid& g) {
  // The arrays' pointers in locals: through the vectors, every store (which may alias them, as
  // far as the compiler knows) reloaded the four data pointers.
  float* const X = g.x.data();
  float* const Y = g.y.data();
  float* const Z = g.z.data();
  std::int32_t* const I = g.ids.data();
  for (std::uint32_t r = rb; r < re; ++r) {
    take_record(rec + 4 * std::size_t(r), X, Y, Z, I, pos[lcell[r - rb]]++);
  }
}

// Sizes the directory and the point arrays (the two-level directory from its segment count).
void size_arrays(const Buckets& bk, const std::vector<std::uint32_t>& seg_base, bool sparse, std::size_t n,
                 Grid& g, GridBuildStats& st) {
  const std::size_t top = Grid::top_entries(bk.ncells);
  if (sparse) {
    const double entries = double(top) + double(seg_base[bk.nb]) * double(1u << BHCL_GRID_SEG_BITS);
    if (entries >= double(BHCL_GRID_EMPTY_SEG))
      throw Error("blockhash grid: the two-level directory would need " + std::to_string(entries) +
                  " entries (at most 2^31): give a larger cell_size");
    g.starts.resize(static_cast<std::size_t>(entries));
    st.occupied_segments = seg_base[bk.nb];
  } else {
    g.starts.resize(bk.ncells + 1);
    g.starts[bk.ncells] = static_cast<std::uint32_t>(n);
    g.starts[0] = 0;
  }
  resize_discarding(g.x, n + kGridPad, 1);
  resize_discarding(g.y, n + kGridPad, 1);
  resize_discarding(g.z, n + kGridPad, 1);
  resize_discarding(g.ids, n + kGridPad, 1);
}

// The buckets cut into `parts` contiguous ranges of about equal work (records, plus a cell for an
// eighth of a record: count_direct's scan): first[w] .. first[w + 1] is range w's.
std::vector<std::size_t> bucket_ranges(const Buckets& bk, std::size_t parts) {
  auto work = [&](std::size_t b) { return double(bk.start[b]) + double(std::min(bk.ncells, b << bk.shift)) / 8; };
  std::vector<std::size_t> first(parts + 1, bk.nb);
  first[0] = 0;
  std::size_t b = 0;
  for (std::size_t w = 1; w < parts; ++w) {
    const double goal = work(bk.nb) * double(w) / double(parts);
    while (b < bk.nb && work(b) < goal) ++b;
    first[w] = b;
  }
  return first;
}

// Pass 3: each bucket on its own, in parallel over buckets: its cells' counts, its part of the
// directory, its points placed (stable). Returns the occupied cells and the sum of squared counts.
// pyramid (a direct directory only): the buckets go to the threads in contiguous ranges, each
// gathering the pyramid of the slabs its range holds whole (PyramidGather); else one at a time.
BucketCounts place_buckets(const Buckets& bk, const std::vector<std::uint32_t>& seg_base, bool sparse,
                           const RecordCell& rec_cell, const float* rec, unsigned threads, Grid& g,
                           PyramidGather* pyramid) {
  const std::size_t nb = bk.nb, ncells = bk.ncells, top = Grid::top_entries(ncells);
  const std::size_t cells_per_bucket = std::size_t(1) << bk.shift;
  const std::size_t seg_per_bucket = std::size_t(1) << (bk.shift - (sparse ? BHCL_GRID_SEG_BITS : 0));
  std::vector<BucketCounts> per(nb);
  auto place = [&](std::size_t b, const PyramidGather::Range* owned) {
    static thread_local BucketScratch ws;
    if (ws.cnt.size() < cells_per_bucket) ws.cnt.assign(cells_per_bucket, 0);
    if (sparse && ws.seg.size() < seg_per_bucket) ws.seg.assign(seg_per_bucket, 0);
    if (sparse && ws.rank.size() < seg_per_bucket) ws.rank.resize(seg_per_bucket);
    const std::size_t c0 = b << bk.shift, c1 = std::min(ncells, c0 + cells_per_bucket);
    const std::uint32_t rb = bk.start[b], re = bk.start[b + 1];
    // The record's cell once per record (the count and the placement both read it): computed
    // twice, the cell took a third of this pass.
    if (ws.lcell.size() < re - rb) ws.lcell.resize(re - rb);
    if (!sparse) {
      per[b] = count_direct(c0, c1, rb, re, rec_cell, ws, g);
      place_records(rb, re, ws.lcell.data(), g.starts.data() + c0 + 1, rec, g);
      if (owned) pyramid->add_cells(g, *owned, c0, c1, rb, g.starts.data() + c0 + 1);  // starts[c + 1]: cell c's end now
      return;
    }
    std::uint32_t nocc = 0;
    per[b] = count_two_level(c0, c1, rb, re, seg_base[b], top, rec_cell, ws, g, &nocc);
    place_records(rb, re, ws.lcell.data(), ws.cnt.data(), rec, g);
    // Clear the counts this bucket used (they became write positions).
    std::fill(ws.cnt.data(), ws.cnt.data() + std::size_t(nocc) * (1u << BHCL_GRID_SEG_BITS), 0u);
  };
  if (pyramid && !sparse) {
    const std::size_t parts = std::max(1u, threads);
    const std::vector<std::size_t> first = bucket_ranges(bk, parts);
    detail::parallel_for(
        parts,
        [&](std::size_t wb, std::size_t we) {
          for (std::size_t w = wb; w < we; ++w) {
            if (first[w] == first[w + 1]) continue;
            const PyramidGather::Range owned =
                pyramid->begin_range(g, first[w] << bk.shift, std::min(ncells, first[w + 1] << bk.shift));
            for (std::size_t b = first[w]; b < first[w + 1]; ++b) place(b, &owned);
          }
        },
        threads, 1);
  } else {
    detail::parallel_chunks(nb, 1, threads, [&](std::size_t b, std::size_t, std::size_t) { place(b, nullptr); });
  }
  // The top entry past the last segment (a run ending at the last cell reads it).
  if (sparse && (ncells & ((std::size_t(1) << BHCL_GRID_SEG_BITS) - 1)) == 0)
    g.starts[top - 1] = BHCL_GRID_EMPTY_SEG | static_cast<std::uint32_t>(g.n_points);
  BucketCounts all;
  for (const BucketCounts& c : per) {
    all.occupied += c.occupied;
    all.sum2 += c.sum2;
  }
  return all;
}

// Whether the input is sorted from its cells' order (count_from_cells, place_from_cells): its
// SoA part in cell order, a direct table of at most a cell per point (the per-range counts then
// stay a few MB, kept in the scratch).
bool sorts_from_cells(const GridInput& in, const bhcl_grid_geom& geom) {
  return in.soa_in_cells && !geom.sparse && cell_count(geom) <= in.size();
}

// A direct table's counting sort for an input whose SoA part is a grid's points in cell order (an
// update's rebuild: a 25 % insert across the band). Ranges of the input (T of the old points, T
// of the new), handed out in turn, each count their cells, then write their points from their
// own starts (the cells' starts plus the earlier ranges' counts): stable in input order, so the
// arrays equal the bucket passes'. The old points' writes move through the new cells as their
// cells moved through the old ones (a window of a few z slabs: near sequential), where the bucket
// passes wrote every point into records and read them back twice. The new points, in no order,
// go through records (one line a point, in a table a fifth of the arrays' size), then are copied
// behind each cell's old points in order (written into the four arrays at random, the update
// took 4-10 % more CPU: the median of 21 rounds in one process, twice).
struct FromCells {
  unsigned T = 1;
  std::size_t R = 2;  // ranges: [0, T) of the old points, [T, 2T) of the new
  std::pair<std::size_t, std::size_t> range(const GridInput& in, std::size_t t) const {
    if (t < T) return {in.n_soa * t / T, in.n_soa * (t + 1) / T};
    t -= T;
    return {in.n_soa + in.n_aos * t / T, in.n_soa + in.n_aos * (t + 1) / T};
  }
};

FromCells ranges_from_cells(std::size_t n, unsigned threads) {
  FromCells fc;
  fc.T = static_cast<unsigned>(std::min<std::size_t>(threads, std::max<std::size_t>(1, n / 65536)));
  fc.R = 2 * std::size_t(fc.T);
  return fc;
}

// Counts each range's cells and makes the directory, the ranges' write positions (in the
// scratch's counts: an old range's slots in the arrays, a new range's in the records), the new
// points' first record per cell (the scratch's add) and the arrays; place_from_cells then writes.
BucketCounts count_from_cells(const GridInput& in, const bhcl_grid_geom& geom, unsigned threads, GridScratch& sc,
                              Grid& g, GridBuildStats& st) {
  auto t0 = std::chrono::steady_clock::now();
  const std::size_t n = in.size(), nc = cell_count(geom);
  const FromCells fc = ranges_from_cells(n, threads);
  const std::size_t R = fc.R, T = fc.T;
  resize_discarding(sc.cell, n, 2);
  resize_discarding(sc.count, R * nc);
  std::uint32_t* const count = sc.count.data();
  std::fill_n(count, R * nc, 0u);
  detail::parallel_chunks(R, 1, fc.T, [&](std::size_t t, std::size_t, std::size_t) {
    const bhcl_grid_geom gg = geom;  // in locals: the stores would reload them through references
    std::uint32_t* const cell = sc.cell.data();
    std::uint32_t* const ct = count + t * nc;
    const auto r = fc.range(in, t);
    for_input(in, r.first, r.second, [&](std::size_t i, float x, float y, float z, std::int32_t) {
      const std::uint32_t c = grid_cell_index(gg, x, y, z);
      cell[i] = c;
      ++ct[c];
    });
  });
  st.t_cells = since(t0);
  t0 = std::chrono::steady_clock::now();
  g.geom = geom;
  g.n_points = n;
  g.starts.resize(nc + 1);
  resize_discarding(sc.add, nc + 1);
  std::uint32_t* const starts = g.starts.data();
  std::uint32_t* const first_rec = sc.add.data();
  BucketCounts bc;
  std::uint32_t k = 0, j = 0;  // the next slot in the arrays, in the records
  for (std::size_t c = 0; c < nc; ++c) {  // count[t][c] becomes range t's first slot of cell c
    starts[c] = k;
    first_rec[c] = j;
    for (std::size_t t = 0; t < T; ++t) {
      const std::uint32_t a = count[t * nc + c];
      count[t * nc + c] = k;
      k += a;
    }
    for (std::size_t t = T; t < R; ++t) {
      const std::uint32_t a = count[t * nc + c];
      count[t * nc + c] = j;
      j += a;
    }
    k += j - first_rec[c];
    const std::uint64_t v = k - starts[c];
    bc.occupied += v ? 1 : 0;
    bc.sum2 += v * v;
  }
  starts[nc] = static_cast<std::uint32_t>(n);
  first_rec[nc] = j;
  resize_discarding(sc.rec, 4 * in.n_aos, 2);
  resize_discarding(g.x, n + kGridPad, 1);
  resize_discarding(g.y, n + kGridPad, 1);
  resize_discarding(g.z, n + kGridPad, 1);
  resize_discarding(g.ids, n + kGridPad, 1);
  st.t_count = since(t0);
  return bc;
}

void place_from_cells(const GridInput& in, unsigned threads, GridScratch& sc, Grid& g) {
  const std::size_t n = in.size(), nc = cell_count(g.geom);
  const FromCells fc = ranges_from_cells(n, threads);
  const std::size_t R = fc.R, T = fc.T;
  std::uint32_t* const count = sc.count.data();
  // The new points' ranges first (their record writes land at random: the slower ranges).
  detail::parallel_chunks(R, 1, fc.T, [&](std::size_t c, std::size_t, std::size_t) {
    const std::size_t t = (c + T) % R;
    float* const X = g.x.data();
    float* const Y = g.y.data();
    float* const Z = g.z.data();
    std::int32_t* const I = g.ids.data();
    float* const rec = sc.rec.data();
    const std::uint32_t* const cell = sc.cell.data();
    std::uint32_t* const at = count + t * nc;
    const auto r = fc.range(in, t);
    if (t >= T) {
      for_input(in, r.first, r.second, [&](std::size_t i, float x, float y, float z, std::int32_t id) {
        put_record(rec + 4 * std::size_t(at[cell[i]]++), x, y, z, id);
      });
      return;
    }
    for_input(in, r.first, r.second, [&](std::size_t i, float x, float y, float z, std::int32_t id) {
      const std::uint32_t slot = at[cell[i]]++;
      X[slot] = x;
      Y[slot] = y;
      Z[slot] = z;
      I[slot] = id;
    });
  });
  if (in.n_aos == 0) return;
  // Each cell's records behind its old points, in parallel over ranges of cells (sequential).
  detail::parallel_for(
      nc,
      [&](std::size_t cb, std::size_t ce) {
        float* const X = g.x.data();
        float* const Y = g.y.data();
        float* const Z = g.z.data();
        std::int32_t* const I = g.ids.data();
        const float* const rec = sc.rec.data();
        const std::uint32_t* const first_rec = sc.add.data();
        const std::uint32_t* const starts = g.starts.data();
        for (std::size_t c = cb; c < ce; ++c) {
          const std::uint32_t j0 = first_rec[c], j1 = first_rec[c + 1];
          for (std::uint32_t j = j0, slot = starts[c + 1] - (j1 - j0); j < j1; ++j, ++slot)
            take_record(rec + 4 * std::size_t(j), X, Y, Z, I, slot);
        }
      },
      fc.T, 1024);
}

}  // namespace

void build_grid(const GridInput& in, const GridBuildArgs& p, Grid& g, GridBuildStats* stats) {
  const std::size_t n = in.size();
  if (n == 0 || n >= (std::size_t(1) << 31) - 1)
    throw Error("blockhash grid: the point count must be in [1, 2^31 - 2], got " + std::to_string(n));
  if (p.directory < -1 || p.directory > 1)
    throw Error("blockhash grid: directory must be -1 (by size), 0 (direct) or 1 (two-level), got " +
                std::to_string(p.directory));
  const unsigned threads = p.threads ? p.threads : detail::default_threads();
  GridBuildStats st;
  auto t0 = std::chrono::steady_clock::now();
  const Box box = bounding_box(in, threads);
  const bhcl_grid_geom geom = grid_shape(in, box, p, st);
  const bool sparse = geom.sparse != 0;
  st.t_tune = since(t0);

  if (!g.scratch) g.scratch = std::make_shared<GridScratch>();
  GridScratch& sc = *g.scratch;
  BucketCounts counts;
  PyramidGather pyramid;  // the pyramid's levels 1 and 2, gathered by the bucket passes' placement
  bool gathered = false;
  if (sorts_from_cells(in, geom)) {
    counts = count_from_cells(in, geom, threads, sc, g, st);
    st.from_cells = true;
    t0 = std::chrono::steady_clock::now();
    place_from_cells(in, threads, sc, g);
    if (in.release) in.release();
  } else {
    const Buckets bk = bucket_records(in, geom, threads, sc, st);
    if (in.release) in.release();  // the input is read: its memory can go before the arrays are sized
    t0 = std::chrono::steady_clock::now();
    g.geom = geom;
    g.n_points = n;
    const RecordCell rec_cell{sc.rec.data(), geom};
    const std::vector<std::uint32_t> seg_base =
        sparse ? number_segments(bk, rec_cell, threads) : std::vector<std::uint32_t>(bk.nb + 1, 0);
    size_arrays(bk, seg_base, sparse, n, g, st);
    gathered = PyramidGather::apply(geom);
    if (gathered) pyramid.start(g);
    counts = place_buckets(bk, seg_base, sparse, rec_cell, sc.rec.data(), threads, g, gathered ? &pyramid : nullptr);
  }
  st.occupied = counts.occupied;
  st.mean_cell_points = double(counts.sum2) / double(n);
  for (std::size_t i = n; i < n + kGridPad; ++i) {
    g.x[i] = g.y[i] = g.z[i] = INFINITY;
    g.ids[i] = -1;
  }
  st.t_scatter = since(t0);
  t0 = std::chrono::steady_clock::now();
  g.dbox = bhcl_grid_dbox{box.lo[0], box.lo[1], box.lo[2], box.hi[0], box.hi[1], box.hi[2]};  // the points stored
  if (gathered)
    pyramid.finish(g, p.threads);
  else
    build_grid_occupancy(g, p.threads);
  st.t_occupancy = since(t0);
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
  if (n_points == 0 || n_points >= (std::size_t(1) << 31) - 1) bad("the point count is out of range");
  const std::size_t nc = ncells();
  if (geom.sparse == 0) {
    if (starts.size() != nc + 1) bad("the cell table has " + std::to_string(starts.size()) + " entries, not cells + 1");
  } else if (geom.sparse == BHCL_GRID_SEG_BITS) {
    const std::size_t top = top_entries(nc), seg = std::size_t(1) << BHCL_GRID_SEG_BITS;
    if (starts.size() < top || (starts.size() - top) % seg != 0 || starts.size() >= BHCL_GRID_EMPTY_SEG)
      bad("the two-level directory has " + std::to_string(starts.size()) + " entries for " + std::to_string(top) + " segments");
    for (std::size_t sg = 0; sg < top; ++sg) {
      const std::uint32_t e = starts[sg];
      if (e & BHCL_GRID_EMPTY_SEG) continue;
      if (e < top || (e - top) % seg != 0 || std::size_t(e) + seg > starts.size())
        bad("segment " + std::to_string(sg) + " points outside the directory");
    }
  } else {
    bad("the directory kind is " + std::to_string(geom.sparse) + " (0 or " + std::to_string(BHCL_GRID_SEG_BITS) + " expected)");
  }
  if (start(0) != 0 || start(nc) != n_points) bad("the cell table does not span the points");
  for (std::size_t c = 0, prev = 0; c <= nc; ++c) {
    const std::size_t v = start(c);
    if (v < prev || v > n_points) bad("the cell table decreases or overruns at cell " + std::to_string(c));
    prev = v;
  }
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
  for (std::size_t c = 0; c < nc; ++c)
    for (std::uint32_t i = start(c), e = start(c + 1); i < e; ++i) {
      std::size_t cx = bhcl_grid_cell(x[i], geom.ox, geom.inv_h, geom.nx);
      std::size_t cy = bhcl_grid_cell(y[i], geom.oy, geom.inv_h, geom.ny);
      std::size_t cz = bhcl_grid_cell(z[i], geom.oz, geom.inv_h, geom.nz);
      if ((cz * geom.ny + cy) * geom.nx + cx != c) bad("point " + std::to_string(i) + " lies outside its cell");
    }
}

}  // namespace bhcl::blockhash
