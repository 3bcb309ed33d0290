// The cell-aligned layout of the auto preset (the talk's future work on clustering): blocks that
// never cross a cell of the primary table, so that a cell's bucket is a short run of blocks holding
// exactly its points. Against Hilbert blocks that straddle the cells (a ~100-point cell touched by
// ~46 blocks), a query tests 5-6x fewer boxes and reads no reference array (docs/PERFORMANCE.md).
#include <algorithm>
#include <cmath>

#include "blockhash/build.hpp"
#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"

namespace bhcl::blockhash {

int axis_threshold_count(const Structure& s, int P, int d) {
  if (!s.info.cell_aligned) return P;
  double top = std::max({s.axis_spread[0], s.axis_spread[1], s.axis_spread[2]});
  if (!(top > 0)) return P;
  double r = s.axis_spread[d] / top;
  return std::clamp(static_cast<int>(std::lround(P * r)), 0, P);
}

void measure_axis_spread(Structure& s, std::size_t stride) {
  std::vector<float> v;
  v.reserve(s.n_points / stride + 1);
  for (int d = 0; d < 3; ++d) {
    v.clear();
    for (std::size_t i = 0; i < s.n_points; i += stride) {
      float p[3];
      s.point(i, p);
      v.push_back(p[d]);
    }
    std::size_t lo = v.size() / 200, hi = v.size() - 1 - v.size() / 200;
    std::nth_element(v.begin(), v.begin() + lo, v.end());
    double a = v[lo];
    std::nth_element(v.begin(), v.begin() + hi, v.end());
    double b = v[hi];
    s.axis_spread[d] = b - a;
  }
}

TableStats build_cell_aligned(const float* xyz, Structure& s) {
  const std::uint32_t P = static_cast<std::uint32_t>(s.info.P);
  const int bits = s.cell_bits();
  const std::size_t n = s.n_points;
  const std::size_t X = static_cast<std::size_t>(s.info.X);
  const float* thr[3] = {s.thr(0, 0), s.thr(0, 1), s.thr(0, 2)};
  // The cell of every point (in parallel), then a counting sort by cell, the cells taken in
  // the Hilbert order of their coordinates: stable, so the points of a cell keep their Hilbert order.
  std::vector<std::uint32_t> cell_of(n);
  detail::parallel_for(n, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const float* p = xyz + 3 * static_cast<std::size_t>(s.order[i]);
      std::uint32_t h[3];
      for (int d = 0; d < 3; ++d) h[d] = hash_coord(thr[d], P, p[d]);
      cell_of[i] = s.cell_key(h);
    }
  });
  const std::uint32_t side = P + 1;
  const std::uint64_t all_cells = std::uint64_t(side) * side * side;
  // Occupied cells: a flag array over the key space when it is small, else a sort of the points.
  std::vector<std::uint32_t> occupied, dense;
  if (all_cells <= (std::uint64_t(1) << 24)) {
    dense.assign(all_cells, 0xffffffffu);
    for (std::size_t i = 0; i < n; ++i) dense[cell_of[i]] = 0;
    for (std::uint64_t c = 0; c < all_cells; ++c)
      if (dense[c] == 0) {
        dense[c] = static_cast<std::uint32_t>(occupied.size());
        occupied.push_back(static_cast<std::uint32_t>(c));
      }
  } else {
    // (cell << 32 | position), sorted in two halves in parallel and merged: the runs are the
    // occupied cells; each position learns its cell's index (kept in `dense`, one per point).
    std::vector<std::uint64_t> kv(n);
    for (std::size_t i = 0; i < n; ++i) kv[i] = (std::uint64_t(cell_of[i]) << 32) | i;
    const std::size_t half = n / 2;
    detail::parallel_for(2, [&](std::size_t part, std::size_t) {
      std::sort(kv.begin() + (part ? half : 0), part ? kv.end() : kv.begin() + half);
    }, 2, 1);
    std::inplace_merge(kv.begin(), kv.begin() + half, kv.end());
    dense.resize(n);
    for (std::size_t j = 0; j < n; ++j) {
      std::uint32_t c = std::uint32_t(kv[j] >> 32);
      if (occupied.empty() || occupied.back() != c) occupied.push_back(c);
      dense[kv[j] & 0xffffffffu] = static_cast<std::uint32_t>(occupied.size() - 1);
    }
  }
  const bool per_point = all_cells > (std::uint64_t(1) << 24);  // dense indexed by position
  std::vector<std::pair<std::uint64_t, std::uint32_t>> by_curve(occupied.size());  // (Hilbert, slot)
  for (std::size_t c = 0; c < occupied.size(); ++c) {
    std::uint32_t key = occupied[c];
    by_curve[c] = {hilbert_encode(key / (side * side), (key / side) % side, key % side, bits),
                   static_cast<std::uint32_t>(c)};
  }
  std::sort(by_curve.begin(), by_curve.end());
  std::vector<std::uint32_t> start(occupied.size() + 1, 0), rank(occupied.size());
  for (std::size_t r = 0; r < by_curve.size(); ++r) rank[by_curve[r].second] = static_cast<std::uint32_t>(r);
  std::vector<std::uint32_t> slot(n);
  for (std::size_t i = 0; i < n; ++i) {
    std::size_t c = per_point ? dense[i] : dense[cell_of[i]];
    slot[i] = rank[c];
    ++start[slot[i] + 1];
  }
  for (std::size_t r = 0; r < occupied.size(); ++r) start[r + 1] += start[r];
  std::vector<std::int32_t> order(n);
  std::vector<std::uint32_t> cells(n);
  std::vector<std::uint64_t> curve(n);
  {
    std::vector<std::uint32_t> fill(start.begin(), start.end() - 1);
    for (std::size_t i = 0; i < n; ++i) {
      std::uint32_t j = fill[slot[i]]++;
      order[j] = s.order[i];
      cells[j] = cell_of[i];
      curve[j] = by_curve[slot[i]].first;
    }
  }
  // Blocks: runs of one cell cut into pieces of X (the last piece of a run partial).
  s.blocks.clear();
  s.boxes.clear();
  s.block_keys.clear();
  struct Run {
    std::uint32_t key, first_block, n_blocks, n_points;
  };
  std::vector<Run> runs;
  for (std::size_t j = 0; j < n;) {
    std::size_t e = j;
    while (e < n && cells[e] == cells[j]) ++e;
    Run run{cells[j], static_cast<std::uint32_t>(s.blocks.size()), 0, static_cast<std::uint32_t>(e - j)};
    for (std::size_t f = j; f < e; f += X) {
      std::size_t end = std::min(e, f + X);
      bhcl_bh_block blk;
      bhcl_bh_box box;
      fill_block(xyz, order, f, end, blk, box);
      s.blocks.push_back(blk);
      s.boxes.push_back(box);
      s.block_keys.push_back(curve[j]);
      ++run.n_blocks;
    }
    runs.push_back(run);
    j = e;
  }
  s.order = std::move(order);
  // Table 0: the occupied cells' keys ascending, each bucket a run of blocks.
  std::sort(runs.begin(), runs.end(), [](const Run& a, const Run& b) { return a.key < b.key; });
  TableStats st;
  s.table_starts = {0, static_cast<std::uint32_t>(runs.size())};
  s.keys.resize(runs.size());
  s.buckets.resize(runs.size());
  s.refs.clear();
  for (std::size_t c = 0; c < runs.size(); ++c) {
    s.keys[c] = runs[c].key;
    s.buckets[c] = bhcl_bh_bucket{runs[c].first_block, runs[c].n_blocks, 0, 0u};
    st.cell_points.push_back(runs[c].n_points);
    st.cell_blocks.push_back(runs[c].n_blocks);
  }
  st.occupied_cells = runs.size();
  return st;
}

CellTable make_cell_table(const Structure& s, std::size_t max_entries) {
  CellTable t;
  if (!s.info.cell_aligned) return t;
  const std::uint32_t P = static_cast<std::uint32_t>(s.info.P);
  std::uint32_t dim[3];
  for (int d = 0; d < 3; ++d) {
    // hash_coord returns at most the count of finite thresholds (the rest are +inf padding).
    const float* th = s.thr(0, d);
    std::uint32_t c = 0;
    while (c < P && std::isfinite(th[c])) ++c;
    dim[d] = c + 1;
  }
  const std::uint64_t cells = std::uint64_t(dim[0]) * dim[1] * dim[2];
  if (cells > max_entries) return t;
  t.dy = dim[1];
  t.dz = dim[2];
  t.runs.assign(2 * cells, 0);
  const std::uint32_t side = P + 1;
  for (std::size_t i = 0; i < s.keys.size(); ++i) {
    std::uint32_t key = s.keys[i];
    std::uint32_t h[3] = {key / (side * side), (key / side) % side, key % side};
    if (h[0] >= dim[0] || h[1] >= dim[1] || h[2] >= dim[2]) return CellTable{};  // not a hash result
    std::uint64_t c = (std::uint64_t(h[0]) * dim[1] + h[1]) * dim[2] + h[2];
    t.runs[2 * c] = s.buckets[i].first_ref;
    t.runs[2 * c + 1] = s.buckets[i].n_refs;
  }
  return t;
}

}  // namespace bhcl::blockhash
